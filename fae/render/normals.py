"""Smooth vertex normals, recomputed every frame from deformed positions."""

from __future__ import annotations

from fae.mesh import vertex_normals as per_vertex_normals  # (V, F, corner_index=None): see fae.mesh

__all__ = ["per_vertex_normals"]
