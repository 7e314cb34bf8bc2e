"""Surface points of the template's meshes: at a vertex, or the closest to a target.

    vertex_point(part, F, vertex) -> SurfacePoint
    closest_point(part, V, F, target) -> SurfacePoint
"""

from __future__ import annotations

import numpy as np

from fae.anatomy.geometry import closest_surface_points
from fae.io.facemodel import SurfacePoint


def vertex_point(part: str, F: np.ndarray, vertex: int) -> SurfacePoint:
    """SurfacePoint exactly at `vertex`, on the lowest-numbered face that uses it."""
    tri = int(np.flatnonzero((F == vertex).any(axis=1))[0])
    bary = (F[tri] == vertex).astype(np.float64)
    return SurfacePoint(part=part, triangle=tri, bary=bary)


def closest_point(part: str, V: np.ndarray, F: np.ndarray, target) -> SurfacePoint:
    """SurfacePoint closest to `target` (3,) on mesh (V, F) (same unit as V)."""
    _, tri, bary = closest_surface_points(V, F, np.asarray(target, dtype=np.float64)[None])
    b = np.clip(bary[0], 0.0, None)
    return SurfacePoint(part=part, triangle=int(tri[0]), bary=b / b.sum())
