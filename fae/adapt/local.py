"""Local adaptation to a pyramid of low-pass filtered scans (paper 001 §IV).

The scan is smoothed by repeated umbrella-Laplacian steps (001 eq. 3, lambda = 0.75); the
model then moves to each pyramid level in turn, coarse to fine, by the nearest-neighbour
operator T_nn. Paper 001 snaps each model vertex onto its nearest scan vertex; fae moves it
to the tangent plane of that vertex instead (its normal component only), which removes the
same distance without pulling model vertices together along the surface. Vertices without
a compatible scan vertex (normals over 90 degrees apart, farther than `max_distance`, on
the scan's boundary, i.e. holes, or not `movable`, e.g. the inside of the mouth, which no
scanner sees) get no target of their own.

Two safeguards keep a head with openings (lip slit, eyelids) valid, which paper 001's
closed test heads did not need:
- the per-vertex offsets are smoothed over the mesh (smooth_offsets): matched vertices
  follow their targets, the others take a smooth fill that fades to zero away from them,
  so the border of the scanned area and of holes does not tear or fold the surface;
- each vertex moves at most `CLEARANCE_SHARE` of its clearance (offset_clearance: the
  distance to the nearest skin across an opening, e.g. from the upper to the lower lip),
  so two facing surfaces cannot pass through each other.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg
from scipy.spatial import cKDTree

from fae.adapt.errors import Surface
from fae.adapt.geometry import adjacency_matrix, per_vertex_normals

CLEARANCE_SHARE = 0.4  # of the gap to the facing surface one vertex may move
FACING_COSINE = -0.3  # normals at least this opposed: the other side of an opening


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
                                max_distance: float, project: str = "plane",
                                movable: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """T_nn: model vertices X (n, 3) with normals NX moved onto the low-pass scan `level_V`.

    Nearest vertices are looked up on the unfiltered scan's KD-tree (the filter moves
    vertices far less than their spacing between neighbouring levels). project: "plane"
    (tangent plane of the nearest vertex) or "vertex" (paper 001's snap). movable (n,)
    bool: vertices allowed a target (default all).
    Returns the new positions (n, 3) and the moved mask (n,).
    """
    cand = np.arange(len(X)) if movable is None else np.flatnonzero(movable)
    dist, j = scan.tree.query(X[cand], distance_upper_bound=max_distance)
    keep = np.isfinite(dist)
    keep[keep] &= ~scan.boundary[j[keep]]
    cand, j = cand[keep], j[keep]
    N = (scan.N if level_V is scan.V else per_vertex_normals(level_V, scan.F))[j]
    facing = np.einsum("nd,nd->n", N, NX[cand]) > 0.0
    cand, j, N = cand[facing], j[facing], N[facing]
    ok = np.zeros(len(X), dtype=bool)
    ok[cand] = True
    Y = X.copy()
    if project == "vertex":
        Y[cand] = level_V[j]
    else:
        off = np.einsum("nd,nd->n", level_V[j] - X[cand], N)
        Y[cand] = X[cand] + off[:, None] * N
    return Y, ok


def offset_clearance(X: np.ndarray, NX: np.ndarray, radius: float, k: int = 24) -> np.ndarray:
    """(n,) metres: distance from each vertex of X (n, 3), unit normals NX (n, 3), to the
    nearest vertex within `radius` whose normal faces it (cosine below FACING_COSINE, i.e.
    the other side of a slit or fold); infinity where there is none."""
    X = np.asarray(X, dtype=np.float64)
    k = min(k, len(X))
    dist, idx = cKDTree(X).query(X, k=k, distance_upper_bound=radius)
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    facing = found & (np.einsum("nd,nkd->nk", NX, NX[idx]) < FACING_COSINE)
    return np.where(facing, dist, np.inf).min(axis=1)


class OffsetSmoother:
    """Solves (W + lam L) D = W O for smooth vertex offsets D (n, 3) on a mesh's graph.

    L is the graph Laplacian of faces F (m, 3) over n vertices, W = diag(weights) with
    weight 1 for matched vertices and `leak` for the rest (their offset fades to zero over
    about sqrt(lam / leak) edges away from matched ones). lam: smoothing, in edges^2;
    rtol: relative residual of the solve (1%: offsets to tens of micrometres, well below
    what one pyramid level changes). Solved by Jacobi-preconditioned conjugate gradients from the previous solution (the
    system changes with the matched set at every pyramid level; a factorization would be
    redone each time).
    """

    def __init__(self, F: np.ndarray, n: int, lam: float = 0.1, leak: float = 1e-3, rtol: float = 1e-2):
        A = adjacency_matrix(np.asarray(F, dtype=np.int64), n)
        self.L = (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()
        self.lam, self.leak, self.n, self.rtol = lam, leak, n, rtol
        self._last = np.zeros((n, 3))

    def __call__(self, offsets: np.ndarray, matched: np.ndarray) -> np.ndarray:
        """(n, 3) smoothed offsets from offsets (n, 3) (ignored where not matched) and matched (n,) bool."""
        w = np.where(matched, 1.0, self.leak)
        M = (sp.diags(w) + self.lam * self.L).tocsr()
        pre = sp.diags(1.0 / M.diagonal())
        rhs = np.where(matched[:, None], offsets, 0.0) * w[:, None]
        out = np.empty((self.n, 3))
        for a in range(3):
            out[:, a], _ = cg(M, rhs[:, a], x0=self._last[:, a], rtol=self.rtol, atol=0.0, M=pre, maxiter=200)
        self._last = out
        return out


def limit_offsets(D: np.ndarray, clearance: np.ndarray, share: float = CLEARANCE_SHARE) -> np.ndarray:
    """(n, 3): offsets D (n, 3) shortened to at most share x clearance (n,) metres each."""
    length = np.linalg.norm(D, axis=1)
    cap = share * clearance
    scale = np.where(length > cap, cap / np.maximum(length, 1e-300), 1.0)
    return D * scale[:, None]
