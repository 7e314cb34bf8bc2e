"""Local adaptation to a pyramid of low-pass filtered scans (paper 001 §IV).

The scan is smoothed by repeated umbrella-Laplacian steps (001 eq. 3, lambda = 0.75); the
model then moves to each pyramid level in turn, coarse to fine, by the nearest-neighbour
operator T_nn. Paper 001 snaps each model vertex onto its nearest scan vertex; fae moves it
to the tangent plane of that vertex instead (its normal component only), which removes the
same distance without pulling model vertices together along the surface. Vertices without
a compatible scan vertex (normals over 90 degrees apart, farther than `max_distance`, or on
the scan's boundary, i.e. holes) stay where they are.
"""

from __future__ import annotations

import numpy as np

from fae.adapt.errors import Surface
from fae.adapt.geometry import adjacency_matrix, per_vertex_normals

import scipy.sparse as sp


def lowpass_pyramid(scan: Surface, lam: float = 0.75, levels: int = 4) -> list[np.ndarray]:
    """Scan vertex positions (n, 3) from coarse to fine: H^(2^(levels-1)) ... H^1, H^0 (the scan)."""
    A = adjacency_matrix(scan.F, len(scan.V))
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    W = (sp.diags(1.0 / deg) @ A).tocsr()
    out = [scan.V]
    X = scan.V.copy()
    done = 0
    for k in range(levels - 1):
        for _ in range(2**k - done if k else 1):
            X = X + lam * (W @ X - X)
        done = 2**k
        out.append(X.copy())
    return out[::-1]


def nearest_neighbor_adaptation(X: np.ndarray, NX: np.ndarray, scan: Surface, level_V: np.ndarray,
                                max_distance: float, project: str = "plane") -> tuple[np.ndarray, np.ndarray]:
    """T_nn: model vertices X (n, 3) with normals NX moved onto the low-pass scan `level_V`.

    Nearest vertices are looked up on the unfiltered scan's KD-tree (the filter moves
    vertices far less than their spacing between neighbouring levels). project: "plane"
    (tangent plane of the nearest vertex) or "vertex" (paper 001's snap).
    Returns the new positions (n, 3) and the moved mask (n,).
    """
    dist, j = scan.tree.query(X, distance_upper_bound=max_distance)
    ok = np.isfinite(dist)
    j = np.where(ok, j, 0)
    N = per_vertex_normals(level_V, scan.F)[j]
    ok &= np.sum(N * NX, 1) > 0.0
    ok &= ~scan.boundary[j]
    Y = X.copy()
    if project == "vertex":
        Y[ok] = level_V[j[ok]]
    else:
        off = np.sum((level_V[j[ok]] - X[ok]) * N[ok], axis=1)
        Y[ok] = X[ok] + off[:, None] * N[ok]
    return Y, ok
