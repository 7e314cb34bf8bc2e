"""Compactly supported RBF offsets with local quadrics (paper 000 §3.3, eq. 11-16, §4.2).

o(x) = sum_j (g_j(x) + c_j) phi_s(|x - p_j|),   phi_s(r) = (1 - r/s)^4_+ (4 r/s + 1)

Paper 000 fits, at each centre p_j, a quadric h(u, v) = A u^2 + 2B uv + C v^2 in a local
(u, v, w) frame (w along the normal) by phi-weighted least squares over its neighbours
(eq. 14-15) and uses g_j as a local approximant that the coefficients c_j correct (eq. 13).
Here the field being interpolated is the displacement D (m, 3), so g_j is the vector-valued
quadric D ~ a + b u + c v + A u^2 + 2B uv + C v^2 fitted the same way (one per coordinate),
divided by the local kernel density sum_k phi_s(|p_j - p_k|) so that sum_j g_j phi_j
already approximates D and c_j is a small correction. The c_j solve the sparse symmetric
positive definite system (Phi + rho I) c = D - G (eq. 13) by conjugate gradients (the paper
uses preconditioned BiCG; CG is its symmetric special case), with a Jacobi preconditioner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator, cg
from scipy.spatial import cKDTree

QUADRIC_DEGREE = 2


def wendland_c2(r: np.ndarray) -> np.ndarray:
    """Wendland's (1 - r)^4_+ (4 r + 1) for normalized distances r >= 0 (eq. 12)."""
    x = np.clip(r, 0.0, 1.0)
    return (1.0 - x) ** 4 * (4.0 * x + 1.0)


def local_frames(N: np.ndarray) -> np.ndarray:
    """(m, 3, 3) rows (u, v, w) of an orthonormal frame per unit normal N (m, 3), w = N."""
    N = np.asarray(N, dtype=np.float64)
    N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(N[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    U = np.cross(N, helper)
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    V = np.cross(N, U)
    return np.stack([U, V, N], axis=1)


def _monomials(uv: np.ndarray) -> np.ndarray:
    u, v = uv[..., 0], uv[..., 1]
    return np.stack([np.ones_like(u), u, v, u * u, 2.0 * u * v, v * v], axis=-1)


def local_quadrics(P: np.ndarray, N: np.ndarray, D: np.ndarray, support: float, k: int = 16,
                   ridge: float = 1e-3, degree: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares quadrics of D around each centre (eq. 14-15).

    P (m, 3) centres, N (m, 3) normals, D (m, 3) displacements, support metres.
    degree: 2 (the paper's quadric), 1 (plane) or 0 (weighted mean); the coefficients of
    higher monomials are then zero.
    Returns frames (m, 3, 3) and coefficients (m, 6, 3) over monomials of (u, v)/support.
    """
    m = len(P)
    frames = local_frames(N)
    k = min(k, m)
    dist, idx = cKDTree(P).query(P, k=k)
    dist, idx = dist.reshape(m, k), idx.reshape(m, k)
    w = wendland_c2(dist / support)  # (m, k)
    rel = P[idx] - P[:, None, :]  # (m, k, 3)
    uv = np.einsum("mkd,mad->mka", rel, frames[:, :2, :]) / support
    M = _monomials(uv)  # (m, k, 6)
    M[..., {0: 1, 1: 3, 2: 6}[degree]:] = 0.0
    MtW = M.transpose(0, 2, 1) * w[:, None, :]
    A = MtW @ M + ridge * np.eye(6)[None]
    B = MtW @ D[idx]  # (m, 6, 3)
    return frames, np.linalg.solve(A, B)


@dataclass
class CSRBF:
    """A fitted compactly supported offset function.

    centers (m, 3) metres; frames (m, 3, 3); quadrics (m, 6, 3) metres; density (m,)
    weights (m, 3) metres; support metres; iterations of the CG solve; tree: KD-tree of
    the centres.
    """

    centers: np.ndarray
    frames: np.ndarray
    quadrics: np.ndarray
    density: np.ndarray
    weights: np.ndarray
    support: float
    iterations: int
    tree: cKDTree | None = None  # of the centres, kept for evaluation


def _pairs(X: np.ndarray, P: np.ndarray, support: float, tree_p: cKDTree | None = None):
    tree_x = cKDTree(X)
    tree_p = tree_p or cKDTree(P)
    s = tree_x.sparse_distance_matrix(tree_p, support, output_type="ndarray")
    return s["i"], s["j"], s["v"]


def _quadric_values(c: CSRBF, X: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    rel = X[i] - c.centers[j]
    uv = np.einsum("nd,nad->na", rel, c.frames[j, :2, :]) / c.support
    return np.einsum("na,nad->nd", _monomials(uv), c.quadrics[j]) / c.density[j, None]


def csrbf_weights(P: np.ndarray, N: np.ndarray, D: np.ndarray, support: float, rho: float = 0.0,
                  tol: float = 1e-4) -> CSRBF:
    """Fit o(p_i) = D_i (eq. 13, 20) for centres P (m, 3), normals N (m, 3), metres.

    support: the Wendland support radius sigma (metres); rho: diagonal regularization.
    """
    P = np.asarray(P, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    m = len(P)
    if m == 0:
        return CSRBF(P, np.zeros((0, 3, 3)), np.zeros((0, 6, 3)), np.zeros(0), np.zeros((0, 3)), support, 0)
    frames, quad = local_quadrics(P, N, D, support, degree=QUADRIC_DEGREE)
    tree = cKDTree(P)
    i, j, r = _pairs(P, P, support, tree)
    phi = wendland_c2(r / support)
    Phi = sp.csr_matrix((phi, (i, j)), shape=(m, m))
    density = np.asarray(Phi.sum(axis=1)).ravel()
    c = CSRBF(P, frames, quad, density, np.zeros((m, 3)), support, 0, tree)
    gv = _quadric_values(c, P, i, j) * phi[:, None]
    G = np.column_stack([np.bincount(i, gv[:, a], minlength=m) for a in range(3)])
    A = (Phi + rho * sp.identity(m, format="csr")).tocsr()
    diag = A.diagonal()
    pre = LinearOperator((m, m), matvec=lambda x: x / diag)
    rhs = D - G
    W = np.zeros((m, 3))
    iters = 0
    for a in range(3):
        count = [0]

        def _cb(_x, count=count):
            count[0] += 1

        W[:, a], _info = cg(A, rhs[:, a], rtol=tol, atol=0.0, M=pre, maxiter=2000, callback=_cb)
        iters = max(iters, count[0])
    c.weights = W
    c.iterations = iters
    return c


def csrbf_interpolant(c: CSRBF, X: np.ndarray) -> np.ndarray:
    """(n, 3) metres: the offset o(X) at points X (n, 3), metres; zero beyond the support."""
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    if len(c.centers) == 0 or n == 0:
        return np.zeros((n, 3))
    i, j, r = _pairs(X, c.centers, c.support, c.tree)
    phi = wendland_c2(r / c.support)
    val = (_quadric_values(c, X, i, j) + c.weights[j]) * phi[:, None]
    return np.column_stack([np.bincount(i, val[:, a], minlength=n) for a in range(3)])
