"""Mesh quantities the fitting needs: normals, boundary, cotangent Laplacian, mean curvature.

libigl-style: arrays in, arrays out. V (n, 3) float64 metres, F (m, 3) int.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def per_vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n, 3) unit area-weighted vertex normals (zero for unreferenced vertices)."""
    V = np.asarray(V, dtype=np.float64)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.column_stack([np.bincount(F.ravel(), np.repeat(fn[:, a], 3), minlength=len(V)) for a in range(3)])
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)


def per_face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 3) unit face normals."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)


def boundary_vertices(F: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: vertices on a boundary edge (an edge used by one face only)."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    key = E[:, 0].astype(np.int64) * n + E[:, 1]
    uniq, count = np.unique(key, return_counts=True)
    b = uniq[count == 1]
    out = np.zeros(n, dtype=bool)
    out[b // n] = True
    out[b % n] = True
    return out


def adjacency_matrix(F: np.ndarray, n: int) -> sp.csr_matrix:
    """(n, n) symmetric 0/1 vertex adjacency."""
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    A = A + A.T
    A.data[:] = 1.0
    return A


def cotmatrix(V: np.ndarray, F: np.ndarray) -> sp.csr_matrix:
    """(n, n) cotangent Laplacian L (L_ij = (cot a_ij + cot b_ij)/2, rows sum to 0)."""
    n = len(V)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = F[:, (k + 1) % 3], F[:, (k + 2) % 3], F[:, k]
        a, b = V[i] - V[o], V[j] - V[o]
        cot = np.sum(a * b, 1) / np.maximum(np.linalg.norm(np.cross(a, b), axis=1), 1e-300)
        rows += [i, j]
        cols += [j, i]
        vals += [0.5 * cot, 0.5 * cot]
    L = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    return L - sp.diags(np.asarray(L.sum(axis=1)).ravel())


def massmatrix(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) barycentric vertex areas (one third of the incident triangle areas)."""
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    return np.bincount(F.ravel(), np.repeat(area / 3.0, 3), minlength=len(V))


def mean_curvature(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) mean curvature (1/metres), Meyer et al.: H = |M^-1 L V| / 2 (paper 000 appendix).

    Positive where the surface bulges outwards along the vertex normal, negative in folds.
    """
    V = np.asarray(V, dtype=np.float64)
    HN = -(cotmatrix(V, F) @ V) / np.maximum(massmatrix(V, F), 1e-300)[:, None]
    N = per_vertex_normals(V, F)
    return 0.5 * np.sign(np.sum(HN * N, 1)) * np.linalg.norm(HN, axis=1)


def laplacian_lowpass(V: np.ndarray, F: np.ndarray, lam: float = 0.75, iterations: int = 1) -> np.ndarray:
    """(n, 3): V after `iterations` steps p <- p + lam * (mean of neighbours - p) (paper 001 eq. 3)."""
    A = adjacency_matrix(F, len(V))
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    W = sp.diags(1.0 / deg) @ A
    X = np.array(V, dtype=np.float64)
    for _ in range(iterations):
        X = X + lam * (W @ X - X)
    return X
