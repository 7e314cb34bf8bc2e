"""Head calibration: pose, scale and unit of a scan from its feature points (paper 000 §3.1).

Paper 000 builds the scan's axes from 8 FDPs (2.1, 11.1, 3.7, 3.12, 8.3, 8.4, 10.9, 10.10).
fae solves the same problem, q* = s R (q - q_c) + p_c (eq. 2-3), as the least-squares
similarity between all feature points the scan and template share (Umeyama 1991), which
needs any 3 non-collinear points and degrades gracefully when some are missing. The scale
is then snapped to a length unit (m, dm, cm, mm, inch) when one is within a factor 1.6, so
the personalized head keeps the person's true size; otherwise the fitted scale is kept and
the unit reported as "unknown".
"""

from __future__ import annotations

import numpy as np

UNITS = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "in": 0.0254}


def similarity_transform(A: np.ndarray, B: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R (3, 3), t (3,) minimizing sum |s R a_i + t - b_i|^2 for A, B (k, 3), k >= 3."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if len(A) < 3:
        raise ValueError(f"calibration needs at least 3 shared feature points, got {len(A)}")
    ma, mb = A.mean(0), B.mean(0)
    a, b = A - ma, B - mb
    U, S, Vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(U @ Vt))
    E = np.diag([1.0, 1.0, d])
    R = U @ E @ Vt
    var = np.sum(a * a)
    if var <= 0:
        raise ValueError("calibration: the scan's feature points all coincide")
    s = float(np.sum(S * np.diag(E)) / var) if with_scale else 1.0
    return s, R, mb - s * R @ ma


def similarity_icp(A: np.ndarray, tree, B: np.ndarray, s: float, R: np.ndarray, t: np.ndarray,
                   iterations: int = 20, keep: float = 0.8, with_scale: bool = True
                   ) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Refine x -> s R x + t mapping points A (n, 3) onto the cloud B (m, 3), `tree` a
    scipy cKDTree over B, by trimmed ICP (the closest `keep` share of pairs; s stays as
    given unless with_scale). Returns s, R, t and the trimmed RMS (in B's unit)."""
    rms = np.inf
    for _ in range(iterations):
        d, j = tree.query(s * A @ R.T + t)
        good = d <= np.quantile(d, keep)
        if with_scale:
            s, R, t = similarity_transform(A[good], B[j[good]])
        else:
            _, R, t = similarity_transform(s * A[good], B[j[good]], with_scale=False)
        rms = float(np.sqrt(np.mean(d[good] ** 2)))
    return s, R, t, rms


def scan_unit(scale: float) -> tuple[str, float]:
    """(unit name, metres per scan unit) for a fitted scan->metres scale; ("unknown", scale)
    when no unit is within a factor 1.6."""
    best = min(UNITS.items(), key=lambda kv: abs(np.log(scale / kv[1])))
    if abs(np.log(scale / best[1])) < np.log(1.6):
        return best
    return "unknown", float(scale)


def calibration_transform(scan_points: np.ndarray, template_points: np.ndarray) -> tuple[np.ndarray, str]:
    """(4, 4) map from scan coordinates to the template's face frame (metres), and the unit.

    scan_points, template_points (k, 3): the same feature points on both. Rotation and
    translation are fitted; the scale is the detected unit (see module docstring).
    """
    s, _, _ = similarity_transform(scan_points, template_points)
    unit, factor = scan_unit(s)
    scaled = np.asarray(scan_points, dtype=np.float64) * factor
    _, R, t = similarity_transform(scaled, template_points, with_scale=False)
    T = np.eye(4)
    T[:3, :3] = R * factor
    T[:3, 3] = t
    return T, unit


def apply_transform(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(n, 3): points X (n, 3) mapped by the 4x4 affine T."""
    return np.asarray(X, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def outlier_landmarks(scan_points: np.ndarray, template_points: np.ndarray, names: list[str],
                      min_error: float = 0.02) -> list[str]:
    """Names of feature points that disagree with the rest (one wrong point, paper 000 §8.4).

    Each point is left out in turn, the similarity is fitted to the others, and the point is
    an outlier when its residual exceeds both `min_error` metres (after the fitted scale)
    and 4 times the median leave-one-out residual. Points in metres-like scale after fit.
    """
    A = np.asarray(scan_points, dtype=np.float64)
    B = np.asarray(template_points, dtype=np.float64)
    k = len(A)
    if k < 6:
        return []
    res = np.empty(k)
    for i in range(k):
        keep = np.arange(k) != i
        s, R, t = similarity_transform(A[keep], B[keep])
        res[i] = np.linalg.norm(s * R @ A[i] + t - B[i])
    med = float(np.median(res))
    bad = (res > min_error) & (res > 4.0 * med)
    # remove only the worst few: a majority of wrong points cannot be detected this way
    order = np.argsort(-res)
    out = [names[i] for i in order[: max(1, k // 5)] if bad[i]]
    return out
