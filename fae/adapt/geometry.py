"""Mesh quantities the fitting needs: normals, boundary, cotangent Laplacian, mean curvature.

libigl-style: arrays in, arrays out. V (n, 3) float64 metres, F (m, 3) int.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def face_normal_vectors(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 3) cross products (V1 - V0) x (V2 - V0) of faces F (m, 3): normal times twice the area."""
    V = np.asarray(V, dtype=np.float64)
    V0 = V[F[:, 0]]
    return np.cross(V[F[:, 1]] - V0, V[F[:, 2]] - V0)


def per_vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n, 3) unit area-weighted vertex normals (zero for unreferenced vertices)."""
    return _unit_rows(_vertex_sums(face_normal_vectors(V, F), F, len(V)))


def per_face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 3) unit face normals."""
    return _unit_rows(face_normal_vectors(V, F))


def _unit_rows(X: np.ndarray) -> np.ndarray:
    return X / np.maximum(np.sqrt(np.einsum("nd,nd->n", X, X)), 1e-300)[:, None]


def _vertex_sums(face_values: np.ndarray, F: np.ndarray, n: int) -> np.ndarray:
    """(n, 3): each face's value (m, 3) added to its three corners."""
    corners = F.ravel()
    return np.column_stack([np.bincount(corners, np.repeat(face_values[:, a], 3), minlength=n) for a in range(3)])


def vertex_face_incidence(F: np.ndarray, n: int) -> sp.csr_matrix:
    """(n, m) sparse 0/1: vertex i is a corner of face f."""
    F = np.asarray(F, dtype=np.int64)
    m = len(F)
    return sp.csr_matrix((np.ones(3 * m), (F.ravel(), np.repeat(np.arange(m), 3))), shape=(n, m))


def per_vertex_normals_at(V: np.ndarray, F: np.ndarray, incidence: sp.csr_matrix, idx: np.ndarray) -> np.ndarray:
    """(k, 3) unit area-weighted normals of the vertices idx (k,) only, from the faces around
    them (incidence: vertex_face_incidence(F, len(V)))."""
    idx = np.asarray(idx, dtype=np.int64)
    start = incidence.indptr[idx]
    count = incidence.indptr[idx + 1] - start
    owner = np.repeat(np.arange(len(idx)), count)
    first = np.cumsum(count) - count
    faces = incidence.indices[np.arange(len(owner)) - np.repeat(first - start, count)]
    fn = face_normal_vectors(V, np.asarray(F)[faces])
    return _unit_rows(np.column_stack([np.bincount(owner, fn[:, a], minlength=len(idx)) for a in range(3)]))


def boundary_vertices(F: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: vertices on a boundary edge (an edge used by one face only)."""
    F = np.asarray(F, dtype=np.int64)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = np.sort(np.minimum(E[:, 0], E[:, 1]) * n + np.maximum(E[:, 0], E[:, 1]))
    repeated = np.zeros(len(key), dtype=bool)
    same = key[1:] == key[:-1]
    repeated[1:] |= same
    repeated[:-1] |= same
    b = key[~repeated]
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


def cotangent_laplacian_of(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n, 3) L V for the cotangent Laplacian L of mesh V (n, 3), F (m, 3)
    (L_ij = (cot a_ij + cot b_ij) / 2, rows summing to 0), without forming L: each face
    adds w (V_j - V_i) to i and w (V_i - V_j) to j for each of its edges ij, w half the
    cotangent of the angle opposite."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    C = [V[F[:, k]] for k in range(3)]
    E = [C[2] - C[1], C[0] - C[2], C[1] - C[0]]  # the edge opposite corner k, from corner k+1 to k+2
    area2 = np.linalg.norm(np.cross(E[2], -E[1]), axis=1)
    half_inv = 0.5 / np.maximum(area2, 1e-300)
    parts = []
    for k in range(3):
        w = -np.einsum("md,md->m", E[(k + 1) % 3], E[(k + 2) % 3]) * half_inv  # cot at corner k / 2
        parts += [E[k] * w[:, None], -E[k] * w[:, None]]
    ends = np.concatenate([F[:, 1], F[:, 2], F[:, 2], F[:, 0], F[:, 0], F[:, 1]])
    vals = np.concatenate(parts)
    return np.column_stack([np.bincount(ends, vals[:, a], minlength=len(V)) for a in range(3)])


def massmatrix(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) barycentric vertex areas (one third of the incident triangle areas)."""
    area = 0.5 * np.linalg.norm(face_normal_vectors(V, F), axis=1)
    return np.bincount(np.asarray(F).ravel(), np.repeat(area / 3.0, 3), minlength=len(V))


def mean_curvature(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) mean curvature (1/metres), Meyer et al.: H = |M^-1 L V| / 2 (paper 000 appendix).

    Positive where the surface bulges outwards along the vertex normal, negative in folds.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    fn = face_normal_vectors(V, F)
    mass = np.bincount(F.ravel(), np.repeat(np.linalg.norm(fn, axis=1) / 6.0, 3), minlength=len(V))
    HN = -cotangent_laplacian_of(V, F) / np.maximum(mass, 1e-300)[:, None]
    outward = np.einsum("nd,nd->n", HN, _vertex_sums(fn, F, len(V)))
    return 0.5 * np.sign(outward) * np.linalg.norm(HN, axis=1)


def laplacian_lowpass(V: np.ndarray, F: np.ndarray, lam: float = 0.75, iterations: int = 1) -> np.ndarray:
    """(n, 3): V after `iterations` steps p <- p + lam * (mean of neighbours - p) (paper 001 eq. 3)."""
    A = adjacency_matrix(F, len(V))
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    W = sp.diags(1.0 / deg) @ A
    X = np.array(V, dtype=np.float64)
    for _ in range(iterations):
        X = X + lam * (W @ X - X)
    return X
