"""Global radial basis function interpolants of a displacement field (dense systems).

Three kernels from the papers, all fitted to displacements D = Q - P at centres P:

- "biharmonic" (paper 000 §3.2, eq. 5-10): phi(r) = r with an affine part R p + t and the
  side conditions sum c = 0, sum c^T p = 0; regularization rho enters as P - rho I (eq. 9;
  phi = r is conditionally negative definite, so -rho smooths).
- "wendland" (paper 001 §III): phi(r) = (1 - r/s)^3_+ (8 + 9 r/s + (r/s)^2) with a linear
  polynomial, support s (default: the centres' bounding-box diagonal, i.e. global);
  regularization +rho I (positive definite kernel).
- "multiquadric" (paper 002): Hardy's h_j(p) = sqrt(|p - p_j|^2 + s_j^2), s_j the distance
  from p_j to its nearest other centre, no polynomial, ridge lambda chosen by generalized
  cross-validation (Golub, Heath, Wahba 1979) over a log grid via one SVD.

Dense O(m^3): meant for up to a few thousand centres; above that use fae.adapt.csrbf.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fae.mesh import coincident_groups, group_means

KERNELS = ("biharmonic", "wendland", "multiquadric")


@dataclass
class RBF:
    """A fitted interpolant.

    kernel   one of KERNELS
    centers  (m, 3) metres
    weights  (m, 3) metres (biharmonic, wendland) or metres per metre (multiquadric)
    affine   (4, 3): rows R^T (3, 3) and t (1, 3); zero for multiquadric
    scale    (m,) metres: multiquadric s_j; support (scalar, metres) for wendland
    ridge    regularization used (rho or the GCV lambda)
    """

    kernel: str
    centers: np.ndarray
    weights: np.ndarray
    affine: np.ndarray
    scale: np.ndarray
    ridge: float


def rbf_kernel(r: np.ndarray, kernel: str, scale: np.ndarray | float = 1.0) -> np.ndarray:
    """phi(r) for distances r (any shape, metres); `scale` is the Wendland support or the
    multiquadric s_j (broadcast against r's last axis)."""
    if kernel == "biharmonic":
        return r
    if kernel == "wendland":
        x = np.clip(r / scale, 0.0, 1.0)
        return (1.0 - x) ** 3 * (8.0 + 9.0 * x + x * x)
    if kernel == "multiquadric":
        return np.sqrt(r * r + np.asarray(scale) ** 2)
    raise ValueError(f"unknown RBF kernel {kernel!r}; expected one of {KERNELS}")


def _distances(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    d2 = np.sum(X * X, 1)[:, None] + np.sum(Y * Y, 1)[None, :] - 2.0 * X @ Y.T
    return np.sqrt(np.maximum(d2, 0.0))


def gcv_ridge(H: np.ndarray, D: np.ndarray, grid: np.ndarray | None = None) -> float:
    """The ridge lambda minimizing generalized cross-validation for H w = D.

    H (m, m) basis matrix, D (m, k) values. GCV(l) = m |(I - A) D|^2 / tr(I - A)^2 with
    A = H (H^T H + l I)^-1 H^T; evaluated for all grid values from one SVD of H.
    """
    U, s, _ = np.linalg.svd(H, full_matrices=False)
    UD = U.T @ D
    outside = np.sum(D * D) - np.sum(UD * UD)  # part of D outside range(H)
    if grid is None:
        grid = np.logspace(-14, 0, 57) * (s[0] ** 2)
    best, best_l = np.inf, float(grid[0])
    m = H.shape[0]
    for lam in grid:
        shrink = lam / (s * s + lam)  # diag of (I - A) in U's basis
        resid = np.sum((shrink[:, None] * UD) ** 2) + max(outside, 0.0)
        trace = np.sum(shrink) + (m - len(s))
        g = m * resid / max(trace, 1e-300) ** 2
        if g < best:
            best, best_l = g, float(lam)
    return best_l


def unique_centers(P: np.ndarray, D: np.ndarray, tol: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Centres closer than `tol` metres merged into one, with their displacements averaged.

    P (m, 3), D (m, 3) -> P' (k, 3), D' (k, 3), k <= m. Coincident centres (e.g. MPEG-4
    feature points that share a vertex: 2.4 and 8.3 on the generic head) make every RBF
    system singular; one centre with the mean displacement is the least-squares answer.
    """
    P = np.asarray(P, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    k, label = coincident_groups(P, tol)
    if k == len(P):
        return P, D
    return group_means(P, label, k), group_means(D, label, k)


def rbf_weights(P: np.ndarray, D: np.ndarray, kernel: str = "biharmonic", rho: float = 0.0,
                support: float | None = None) -> RBF:
    """Fit the interpolant of displacements D (m, 3) at centres P (m, 3), metres.

    rho: regularization (biharmonic, wendland); ignored for multiquadric (GCV picks it).
    support: Wendland support radius in metres (default: bounding-box diagonal of P).
    Coincident centres are merged first (unique_centers).
    """
    P = np.asarray(P, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    if P.shape != D.shape or P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"rbf_weights: centres {P.shape} and displacements {D.shape} must both be (m, 3)")
    P, D = unique_centers(P, D)
    m = len(P)
    R = _distances(P, P)
    if kernel == "multiquadric":
        if m < 2:
            raise ValueError("rbf_weights: the multiquadric kernel needs at least 2 centres")
        s = cKDTree(P).query(P, k=2)[0][:, 1]
        H = rbf_kernel(R, kernel, s[None, :])
        lam = gcv_ridge(H, D)
        W = np.linalg.solve(H.T @ H + lam * np.eye(m), H.T @ D)
        return RBF(kernel, P, W, np.zeros((4, 3)), s, lam)
    if m < 4:
        raise ValueError(f"rbf_weights: the {kernel} kernel with an affine part needs at least 4 centres, got {m}")
    scale = support if support is not None else float(np.linalg.norm(np.ptp(P, axis=0))) * 1.5
    A = np.zeros((m + 4, m + 4))
    A[:m, :m] = rbf_kernel(R, kernel, scale)
    A[:m, :m] += (-rho if kernel == "biharmonic" else rho) * np.eye(m)
    Q = np.hstack([P, np.ones((m, 1))])
    A[:m, m:] = Q
    A[m:, :m] = Q.T
    B = np.vstack([D, np.zeros((4, 3))])
    try:
        X = np.linalg.solve(A, B)
    except np.linalg.LinAlgError:  # coincident centres or coplanar ones: least-squares solution
        X = np.linalg.lstsq(A, B, rcond=None)[0]
    return RBF(kernel, P, X[:m], X[m:], np.full(m, scale), float(rho))


def rbf_interpolant(rbf: RBF, X: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """(n, 3) metres: the fitted displacement at points X (n, 3), metres."""
    X = np.asarray(X, dtype=np.float64)
    out = np.empty((len(X), 3))
    for a in range(0, len(X), chunk):
        x = X[a:a + chunk]
        R = _distances(x, rbf.centers)
        scale = rbf.scale[None, :] if rbf.kernel == "multiquadric" else rbf.scale[0]
        out[a:a + chunk] = rbf_kernel(R, rbf.kernel, scale) @ rbf.weights + x @ rbf.affine[:3] + rbf.affine[3]
    return out
