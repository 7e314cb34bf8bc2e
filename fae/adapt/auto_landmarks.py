"""Feature points found on a scan without any given (paper 003).

    auto_landmarks(template, scan_V, scan_F, method="fit") -> (FDP name -> (3,) in the scan's
                                                              frame and unit, report dict)

1. Pose and unit (rough_alignment): for every length unit, the scan's principal axes
   are matched to the template face's in each of the 24 proper axis assignments, each
   start is refined by rigid ICP of the scan into the template's visible skin, and the
   start with the smallest two-way trimmed RMS wins.
2. The robust point (paper 003 detects a few points first and keeps them): the nose tip
   9.3, the scan's most forward point within NOSE_SEARCH metres of the aligned
   template's nose tip.
3. The other feature points start as the aligned template's, moved to the closest scan
   point, and are refined by one of:
   - "ga": paper 003's genetic algorithm: genes are tangent-plane offsets of every
     feature point but the fixed ones; the fitness is the inverse of the surface error
     between the template morphed by an RBF through the candidate points and the scan,
     measured along cylindrical projections about the vertical axis (rays
     perpendicular to it through evenly spread samples of the front of the face; no
     neck, no back of the head); multi-point crossover, mutation rate starting at 0.3 and
     rising while the best error stalls, each candidate projected onto the scan.
   - "fit" (default): the template's own fit (fae.adapt.multilevel) with the current
     points as soft constraints (regularization `rho`, so the surface pairs can slide
     them), the points read off the fitted skin (they are surface points of the
     template), repeated `rounds` times.
   tools/bench_adapt.py --auto compares both with the aligned template's points on the
   same scans. Measured: neither refinement gains much over the alignment on smoothly
   warped faces (median errors 6-8 mm; the nose tip about 1.5 mm), "fit" a little, the
   GA not at all: away from distinct shapes, the surface error does not tell where a
   point belongs.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
from scipy.spatial import cKDTree

from fae.adapt.calibration import apply_transform, scan_unit, similarity_transform
from fae.adapt.errors import surface
from fae.adapt.query import MeshQuery
from fae.adapt.rbf import rbf_interpolant, rbf_weights
from fae.anatomy.surface_points import markup_positions
from fae.io.facemodel import FaceModel

NOSE_SEARCH = 0.02  # m around the aligned template's nose tip
FIXED = ("9.3",)  # detected points the refinement keeps
METHODS = ("fit", "ga")


def _proper_axis_maps() -> list[np.ndarray]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            M[np.arange(3), perm] = signs
            if np.linalg.det(M) > 0:
                out.append(M)
    return out


def _principal_axes(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = X.mean(axis=0)
    _, _, Vt = np.linalg.svd(X - c, full_matrices=False)
    return c, Vt  # rows: axes by decreasing spread


def rough_alignment(template_V: np.ndarray, face_V: np.ndarray, scan_V: np.ndarray) -> tuple[np.ndarray, str, float]:
    """(4, 4) scan -> template face frame (metres), the unit name and the alignment error (m).

    template_V (n, 3): the template's visible skin, metres; face_V (k, 3): its front of
    the face; scan_V (m, 3): any frame and unit. Every length unit's scale (and the
    scale that matches spreads) is tried with the 24 proper maps of principal axes, each
    refined by a few rigid ICP steps of the scan into the template; the score is the
    trimmed RMS both ways (scan -> template skin, template face -> scan), so a scan shrunk
    into a corner of the head cannot win. The best starts get a longer ICP.
    """
    from fae.adapt.calibration import UNITS

    S = np.asarray(scan_V, dtype=np.float64)
    probe = S[:: max(1, len(S) // 1500)]
    cs, As = _principal_axes(probe)
    cf, Af = _principal_axes(face_V)
    tree = cKDTree(template_V)
    spread = np.sqrt(np.sum(np.var(face_V, axis=0)) / max(np.sum(np.var(probe, axis=0)), 1e-300))
    # the unit whose scale is nearest the spread ratio, its neighbours, and the ratio itself
    near = sorted(UNITS.values(), key=lambda u: abs(np.log(u / spread)))[:2]
    scales = sorted(set(near + [float(spread)]))
    face_probe = face_V[:: max(1, len(face_V) // 800)]

    def score(s, R, t):
        Y = s * probe @ R.T + t
        d1 = tree.query(Y)[0]
        d2 = cKDTree(Y).query(face_probe)[0]
        trim = lambda d: float(np.sqrt(np.mean(np.sort(d)[: max(1, int(0.8 * len(d)))] ** 2)))
        return trim(d1) + trim(d2)

    starts = []
    for s in scales:
        for M in _proper_axis_maps():
            R = Af.T @ M @ As
            t = cf - s * R @ cs
            _, R, t, _ = _rigid_icp(probe * s, tree, template_V, R, t, iterations=5)
            starts.append((score(s, R, t), s, R, t))
    starts.sort(key=lambda x: x[0])
    best = (np.inf, None)
    for _, s, R, t in starts[:4]:
        _, R, t, _ = _rigid_icp(probe * s, tree, template_V, R, t, iterations=25)
        e = score(s, R, t)
        if e < best[0]:
            best = (e, (s, R, t))
    e, (s, R, t) = best
    unit, _ = scan_unit(s)
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = t
    return T, unit, float(e)


def _rigid_icp(A, tree, B, R, t, iterations: int = 15, keep: float = 0.8):
    rms = np.inf
    for _ in range(iterations):
        Y = A @ R.T + t
        d, j = tree.query(Y)
        good = d <= np.quantile(d, keep)
        _, R, t = similarity_transform(A[good], B[j[good]], with_scale=False)
        rms = float(np.sqrt(np.mean(d[good] ** 2)))
    return 1.0, R, t, rms


def _front_samples(V: np.ndarray, seen: np.ndarray, fdp: dict[str, np.ndarray], spacing: float) -> np.ndarray:
    """Indices of evenly spread visible template vertices on the front of the face (between
    the chin and the top of the forehead, in front of the ears)."""
    lo = fdp["2.1"][1] if "2.1" in fdp else V[:, 1].min()
    hi = fdp["11.1"][1] if "11.1" in fdp else V[:, 1].max()
    zmin = min(fdp[n][2] for n in ("10.9", "10.10") if n in fdp) if "10.9" in fdp else np.median(V[:, 2])
    front = seen & (V[:, 1] >= lo) & (V[:, 1] <= hi) & (V[:, 2] >= zmin)
    idx = np.flatnonzero(front)
    cell = np.floor(V[idx] / spacing).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    return idx[np.sort(first)]


class CylindricalError:
    """Paper 003's error: samples P (s, 3) of the template, morphed by an RBF through the
    feature points, against the scan along rays perpendicular to the vertical axis through
    `centre` (3,). E = mean squared distance, misses (holes, outside the scan) count as
    `miss` metres."""

    def __init__(self, samples: np.ndarray, scan: MeshQuery, centre: np.ndarray, miss: float = 0.01):
        self.P = samples
        self.scan = scan
        self.centre = centre
        self.miss = miss

    def __call__(self, PL: np.ndarray, QL: np.ndarray) -> float:
        X = self.P + rbf_interpolant(rbf_weights(PL, QL - PL, "biharmonic", rho=1e-6), self.P)
        radial = X - self.centre
        radial[:, 1] = 0.0
        r = np.linalg.norm(radial, axis=1)
        u = radial / np.maximum(r, 1e-12)[:, None]
        origin = X.copy()
        origin[:, [0, 2]] = self.centre[[0, 2]]
        hit, t, _, _ = self.scan.ray_hits(origin, u, 1.0)
        d = np.where(hit, np.abs(t - r), self.miss)
        return float(np.mean(np.minimum(d, self.miss) ** 2))


def ga_refine(PL: np.ndarray, Q0: np.ndarray, fixed: np.ndarray, error: CylindricalError, project,
              radius: float = 0.006, population: int = 24, generations: int = 30, seed: int = 0
              ) -> tuple[np.ndarray, list[float]]:
    """Paper 003's GA over scan feature points Q0 (k, 3) (template points PL): genes are
    offsets (k, 3) within `radius` metres of Q0 (zero where `fixed`), each candidate is
    projected onto the scan by `project`. Returns the best points (k, 3) and the best
    error per generation."""
    rng = np.random.default_rng(seed)
    k = len(Q0)
    free = ~fixed

    def make(offsets):
        return project(Q0 + offsets * free[:, None])

    pop = [np.zeros((k, 3))] + [rng.normal(scale=radius / 2, size=(k, 3)) for _ in range(population - 1)]
    cand = [make(o) for o in pop]
    fit = np.array([error(PL, q) for q in cand])
    history = [float(fit.min())]
    rate = 0.3
    for _ in range(generations):
        order = np.argsort(fit)
        elite = [cand[i] for i in order[:2]]
        children = list(elite)
        while len(children) < population:
            a, b = (min(rng.choice(population, 3, replace=False), key=lambda i: fit[i]) for _ in range(2))
            cuts = np.sort(rng.choice(np.arange(1, k), size=min(3, k - 1), replace=False))
            take = np.zeros(k, dtype=bool)
            for j, c in enumerate(cuts):  # multi-point crossover: alternate segments
                if j % 2 == 0:
                    take[c:] = ~take[c:]
            child = np.where(take[:, None], cand[b], cand[a])
            mutate = (rng.random(k) < rate) & free
            child = child + mutate[:, None] * rng.normal(scale=radius / 3, size=(k, 3))
            off = np.clip(child - Q0, -radius, radius)
            children.append(make(off))
        cand = children
        fit = np.array([error(PL, q) for q in cand])
        history.append(float(fit.min()))
        # the paper raises the mutation rate while the error stays, lowers it on progress
        rate = min(0.6, rate * 1.2) if history[-1] >= history[-2] - 1e-12 else max(0.1, rate * 0.8)
    return cand[int(np.argmin(fit))], history


def auto_landmarks(template: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray, method: str = "fit",
                   rounds: int = 2, seed: int = 0, rho: float = 0.03, levels: int = 2
                   ) -> tuple[dict[str, np.ndarray], dict]:
    """Feature points on a scan (V (n, 3), F (m, 3), any frame and unit) for the template's
    skin FDPs, in the scan's frame and unit, and a report (see module docstring).

    rounds, rho, levels: of the "fit" refinement (rounds=0: the aligned template's points,
    projected onto the scan); seed: of the GA."""
    from fae.adapt.multilevel import fit_template
    from fae.adapt.transfer import visible_skin

    if method not in METHODS:
        raise ValueError(f"unknown feature point search {method!r}; expected one of {METHODS}")
    t0 = time.perf_counter()
    V, F = template.skin_vertices, template.skin_faces.astype(np.int64)
    seen = visible_skin(template)
    fdp = {n: p for n, p in markup_positions(template).items() if template.feature_points[n].part == "skin"}
    face = _front_samples(V, seen, fdp, 0.004)
    T, unit, rms = rough_alignment(V[seen], V[face], scan_V)
    SV = apply_transform(T, scan_V)
    scan = surface(SV, scan_F)
    names = [n for n in fdp if seen[F[template.feature_points[n].triangle]].any()]
    PL = np.array([fdp[n] for n in names])
    Q, dist, _, _ = scan.query.closest_points(PL)
    near = np.isfinite(dist) & (dist < 0.02)
    names = [n for n, ok in zip(names, near) if ok]
    PL, Q = PL[near], Q[near]
    # the robust point: the nose tip is the most forward scan point near the template's
    detected = {}
    if "9.3" in names:
        i = names.index("9.3")
        around = scan.tree.query_ball_point(PL[i], NOSE_SEARCH)
        if around:
            j = around[int(np.argmax(SV[around, 2]))]
            Q[i] = SV[j]
            detected["9.3"] = "most forward scan point near the aligned template's nose tip"
    fixed = np.array([n in detected for n in names])

    def project(X):
        return scan.query.closest_points(X)[0]

    history: list[float] = []
    if method == "ga":
        sample_idx = _front_samples(V, seen, fdp, 0.008)
        centre = 0.5 * (V.min(axis=0) + V.max(axis=0))
        error = CylindricalError(V[sample_idx], scan.query, centre)
        Q, history = ga_refine(PL, Q, fixed, error, project, seed=seed)
    else:
        for _ in range(rounds):
            fit = fit_template(V, F, PL, SV, scan_F, Q, levels=levels, local_levels=3, movable=seen, rho=rho)
            Xf = fit.vertices
            new = np.array([template.feature_points[n].bary @ Xf[F[template.feature_points[n].triangle]]
                            for n in names])
            Q = np.where(fixed[:, None], Q, project(new))
            history.append(fit.final["combined_error"])
    inverse = np.linalg.inv(T)
    out = {n: apply_transform(inverse, Q[i][None])[0] for i, n in enumerate(names)}
    report = {"method": method, "scan_unit": unit, "alignment_rms": rms, "detected": detected,
              "refined": [n for n in names if n not in detected], "errors": history,
              "seconds": time.perf_counter() - t0}
    return out, report
