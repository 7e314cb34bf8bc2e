"""Smooth vertex normals, recomputed every frame from deformed positions."""

from __future__ import annotations

import numpy as np


def per_vertex_normals(V: np.ndarray, F: np.ndarray, corner_index: np.ndarray | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals.

    V  (n, 3) float, vertex positions (any unit)
    F  (m, 3) int, counter-clockwise triangles
    corner_index  optional (3m,) int64 `F.ravel()`, precomputed by callers that run this
        every frame
    Returns (n, 3) float64 unit vectors; a vertex on no (or only degenerate) triangles gets
    (0, 0, 1).

    Sums face normals with `np.bincount` (a scatter-add about 2.5x faster than np.add.at).
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if corner_index is None:
        corner_index = F.ravel().astype(np.int64)
    a = V[F[:, 0]]
    face_n = np.cross(V[F[:, 1]] - a, V[F[:, 2]] - a)  # length = 2 * area: area weighting
    n = V.shape[0]
    N = np.empty((n, 3))
    for k in range(3):
        N[:, k] = np.bincount(corner_index, weights=np.repeat(face_n[:, k], 3), minlength=n)
    length = np.sqrt(np.einsum("ij,ij->i", N, N))
    bad = length < 1e-30
    N[bad] = (0.0, 0.0, 1.0)
    length[bad] = 1.0
    N /= length[:, None]
    return N
