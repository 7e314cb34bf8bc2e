"""The fitting pipeline: template surface -> calibrated scan, level by level (paper 000 §4).

Level 0 is a global RBF through the feature-point pairs. Each further level adds pairs
(feature-mesh subdivision + ray casting, mean-curvature features; fae.adapt.correspondence)
and fits either a new global RBF (below GLOBAL_LIMIT pairs) or a CSRBF offset with halved
support on top of the previous function (eq. 17-21). Then optional local adaptation to a
low-pass pyramid (paper 001). Errors (paper 000 §5) are measured after every level and the
result with the smallest combined error is returned, after fae.adapt.untangle has blended
it back towards the first level wherever it cuts through itself (reported as
`relaxed_vertices`); vertices that coincide on the template (seams) are averaged back
together first.

Correspondences per level k: the feature points, feature-mesh ray pairs (paper 000 §4.1),
mean-curvature features, and closest-point pairs from template vertices sampled every
SURFACE_SPACING / 2^(k-1) metres (the feature mesh only covers the area between feature
points; these reach the forehead, sides and neck). Pairs whose residual is far beyond the
others' (consistent_pairs) are dropped: they matched the wrong sheet of the scan.

Methods (all given the same feature points):
  "multilevel"   paper 000 levels (biharmonic RBF, then CSRBF) + paper 001 local step
  "rbf"          paper 000 approach 1 only: one biharmonic RBF through the feature points
  "wendland"     paper 001: global Wendland RBF + local low-pass adaptation
  "multiquadric" paper 002: Hardy multiquadric RBF, ridge by GCV
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from fae.adapt import PAPER_METHODS
from fae.adapt.correspondence import (closest_pairs, curvature_features, feature_mesh, feature_mesh_samples,
                                     grid_sample, ray_pairs)
from fae.adapt.csrbf import CSRBF, csrbf_interpolant, csrbf_weights
from fae.adapt.errors import (Surface, combined_error, compatible_closest_points, distance_error,
                              marker_error, surface, symmetric_rms)
from fae.adapt.geometry import per_vertex_normals
from fae.adapt.local import (OffsetSmoother, limit_offsets, lowpass_pyramid, nearest_neighbor_adaptation,
                             offset_clearance)
from fae.adapt.query import MeshQuery
from fae.adapt.rbf import RBF, rbf_interpolant, rbf_weights
from fae.adapt.untangle import along_seams, edge_crossings, mesh_edges, untangle
from fae.mesh import coincident_groups, group_means

METHODS = PAPER_METHODS
GLOBAL_LIMIT = 500  # paper 000 §4.3: global RBF below this many pairs, CSRBF above
CSRBF_RHO = 1e-2  # diagonal regularization of each CSRBF level (Phi's diagonal is 1)
CSRBF_TOL = 1e-3  # relative CG residual: finer detail is the local step's job
SURFACE_SPACING = 0.01  # m: closest-point pairs every 10 mm at level 1, halved per level
SUPPORT_MAX = 4.0  # CSRBF support at most this many times the pairs' median spacing


@dataclass
class Deformation:
    """x -> x + sum of the level functions: a global RBF followed by CSRBF offsets, all
    evaluated at template-frame points (metres)."""

    base: RBF
    offsets: list[CSRBF] = field(default_factory=list)

    def displacement(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) metres at template points X (n, 3)."""
        D = rbf_interpolant(self.base, X)
        for o in self.offsets:
            D += csrbf_interpolant(o, X)
        return D

    def __call__(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        return X + self.displacement(X)


@dataclass
class Fit:
    """Result of fit_template.

    vertices (n, 3) metres: the fitted template skin; deformation: the level functions
    (maps any template-frame point, e.g. bones, without the local step); levels: per-level
    report dicts; final: final report dict; chosen_level: index into levels;
    dropped_landmarks: indices of feature points left out because they folded the skin.
    """

    vertices: np.ndarray
    deformation: Deformation
    levels: list[dict]
    final: dict
    chosen_level: int
    dropped_landmarks: list[int] = field(default_factory=list)


def fit_template(P: np.ndarray, F: np.ndarray, P_landmarks: np.ndarray, scan_V: np.ndarray,
                 scan_F: np.ndarray, Q_landmarks: np.ndarray, method: str = "multilevel",
                 levels: int = 1, local_levels: int = 4, rho: float = 0.0,
                 progress: Callable[[str], None] | None = None, movable: np.ndarray | None = None,
                 scan: Surface | None = None) -> Fit:
    """Fit template surface P (n, 3), F (m, 3) to a scan already in the face frame.

    P_landmarks (k, 3) and Q_landmarks (k, 3): the same feature points on template and scan,
    metres. levels: refinement levels after the first (multilevel only); local_levels:
    pyramid levels of the local step (multilevel, wendland; 0 disables it). movable (n,)
    bool: template vertices the local step may match to the scan (default all; a head
    passes False for surfaces no scanner sees, such as the inside of the mouth). scan: the
    scan already prepared by fae.adapt.errors.surface(scan_V, scan_F), when it is.
    """
    if method not in METHODS:
        raise ValueError(f"unknown adaptation method {method!r}; expected one of {METHODS}")
    t0 = time.perf_counter()
    P = np.asarray(P, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    PL = np.asarray(P_landmarks, dtype=np.float64)
    QL = np.asarray(Q_landmarks, dtype=np.float64)
    if scan is None:
        scan = surface(scan_V, scan_F)
    width = float(np.ptp(P[:, 0]))  # the face frame's x: ear to ear
    max_distance = width / 10.0
    NP = per_vertex_normals(P, F)
    centre = 0.5 * (P.min(0) + P.max(0))
    scored = np.ones(len(P), dtype=bool) if movable is None else np.asarray(movable, dtype=bool)
    report: list[dict] = []
    results: list[tuple[np.ndarray, Deformation]] = []

    matches: list[tuple[np.ndarray, np.ndarray]] = []  # per level: distance (n,) and compatibility (n,) of X

    def evaluate(X: np.ndarray, deformation: Deformation, pairs: int, lm_now: np.ndarray) -> None:
        NX = per_vertex_normals(X, F)
        _, _, dist, ok = compatible_closest_points(X[scored], NX[scored], scan, max_distance)
        full_dist, full_ok = np.full(len(X), np.inf), np.zeros(len(X), dtype=bool)
        full_dist[scored], full_ok[scored] = dist, ok
        matches.append((full_dist, full_ok))
        de = distance_error(dist, ok.astype(float))
        me = marker_error(lm_now, QL)
        report.append({"level": len(report), "pairs": int(pairs), "distance_error": de, "marker_error": me,
                       "combined_error": combined_error(de, me), "matched_fraction": float(ok.mean()),
                       "seconds": time.perf_counter() - t0})
        results.append((X, deformation))
        if progress:
            progress(f"level {len(report) - 1}: {pairs} pairs, combined error {report[-1]['combined_error']:.3g} m")

    seams, seam = coincident_groups(P)
    kernel = {"multilevel": "biharmonic", "rbf": "biharmonic", "wendland": "wendland",
              "multiquadric": "multiquadric"}[method]
    E = mesh_edges(F)
    model_query = MeshQuery(P, F)  # of the fitted surface, moved along (refits, not rebuilds)
    deformation, dropped, level0_clean = folding_free_rbf(P, F, PL, QL, kernel, rho, E, model_query)
    if dropped:
        keep = np.setdiff1d(np.arange(len(PL)), dropped)
        PL, QL = PL[keep], QL[keep]
    X = deformation(P)
    XL = deformation(PL)
    evaluate(X, deformation, len(PL), XL)

    if method == "multilevel" and levels > 0:
        T = feature_mesh(PL, centre)
        NL = NP[_nearest(P, PL)]
        box_min, box_max = QL.min(0), QL.max(0)
        spacing = width / 40.0
        curv = curvature_features(scan, box_min, box_max, 200, spacing)
        support = width / 2.0
        can_match = np.ones(len(P), dtype=bool) if movable is None else np.asarray(movable, dtype=bool)
        for k in range(1, levels + 1):
            origins, dirs = feature_mesh_samples(XL, T, k)
            model = surface(X, F, model_query)
            fm, bm, qs, _ = ray_pairs(origins, dirs, model, scan, max_distance)
            fc, bc, qc, _ = ray_pairs(scan.V[curv], scan.N[curv], model, scan, max_distance)
            face = np.concatenate([fm, fc])
            bary = np.concatenate([bm, bc])
            seen = can_match[F[face]].all(axis=1)  # no pairs on skin the scan cannot show
            face, bary = face[seen], bary[seen]
            q_rays = np.vstack([qs, qc])[seen]
            vs, qv = closest_pairs(X, model.N, scan, max_distance,
                                   grid_sample(P, SURFACE_SPACING / 2 ** (k - 1), can_match))
            p_new = np.vstack([np.einsum("nk,nkd->nd", bary, P[F[face]]), P[vs]])
            n_new = np.vstack([np.einsum("nk,nkd->nd", bary, NP[F[face]]), NP[vs]])
            q_new = np.vstack([q_rays, qv])
            keep = consistent_pairs(deformation(p_new), q_new)
            p_new, n_new, q_new = p_new[keep], n_new[keep], q_new[keep]
            p_all = np.vstack([PL, p_new])
            q_all = np.vstack([QL, q_new])
            m = len(p_all)
            if m < GLOBAL_LIMIT:
                deformation = Deformation(rbf_weights(p_all, q_all - p_all, "biharmonic", rho=rho))
                X, XL = deformation(P), deformation(PL)
            else:
                n_all = np.vstack([NL, n_new])
                resid = q_all - deformation(p_all)
                from scipy.spatial import cKDTree
                spacing_pairs = float(np.median(cKDTree(p_all).query(p_all, k=2)[0][:, 1]))
                support = max(min(support / 2.0, SUPPORT_MAX * spacing_pairs), 3.0 * spacing_pairs)
                off = csrbf_weights(p_all, n_all, resid, support, rho=CSRBF_RHO, tol=CSRBF_TOL)
                deformation = Deformation(deformation.base, deformation.offsets + [off])
                X, XL = X + csrbf_interpolant(off, P), XL + csrbf_interpolant(off, PL)
            evaluate(X, deformation, m, XL)
            if len(report) >= 3 and report[-1]["combined_error"] > report[-2]["combined_error"] > report[-3]["combined_error"]:
                break

    best = int(np.argmin([r["combined_error"] for r in report]))
    X, deformation = results[best]
    if method in ("multilevel", "wendland") and local_levels > 0:
        model_query.move(X)
        _, _, lm_face, lm_bary = model_query.closest_points(deformation(PL))
        lm_face = np.maximum(lm_face, 0)
        X0 = X
        clearance = offset_clearance(X0, per_vertex_normals(X0, F), width / 20.0)
        smoother = OffsetSmoother(F, len(X0))
        for level_V in lowpass_pyramid(scan, levels=local_levels):
            NX = per_vertex_normals(X, F)
            Y, moved = nearest_neighbor_adaptation(X, NX, scan, level_V, max_distance, movable=movable)
            X = X0 + limit_offsets(X - X0 + smoother(Y - X, moved), clearance)
            lm_now = np.einsum("nk,nkd->nd", lm_bary, X[F[lm_face]])
            evaluate(X, deformation, int(moved.sum()), lm_now)
        best = int(np.argmin([r["combined_error"] for r in report]))
    X, deformation = results[best]
    if seams < len(P):  # vertices that coincide on the template (seams) coincide on the fit
        X = group_means(X, seam, seams)[seam]
    relaxed = 0
    if best > 0:  # blend back wherever the chosen level cuts through itself
        X, weight = untangle(F, X, results[0][0] if level0_clean else P, edges=E, query=model_query)
        relaxed = int(np.sum(weight < 1.0))
    model = surface(X, F, model_query)
    # the chosen level's distances hold wherever welding and untangling left X and its normals alone
    changed = np.any(X != results[best][0], axis=1)
    changed[F[changed[F].any(axis=1)].ravel()] = True
    dist, ok = (a.copy() for a in matches[best])
    redo = np.flatnonzero(changed & scored)
    _, _, dist[redo], ok[redo] = compatible_closest_points(X[redo], model.N[redo], scan, max_distance)
    final = symmetric_rms(model, scan, max_distance, scored, model_match=(dist, ok))
    final["relaxed_vertices"] = relaxed
    final["marker_error"] = report[best]["marker_error"]
    final["distance_error"] = report[best]["distance_error"]
    final["combined_error"] = report[best]["combined_error"]
    final["seconds"] = time.perf_counter() - t0
    final["method"] = method
    return Fit(X, deformation, report, final, best, dropped)


def folding_free_rbf(P: np.ndarray, F: np.ndarray, PL: np.ndarray, QL: np.ndarray, kernel: str, rho: float,
                     edges: np.ndarray | None = None, query: MeshQuery | None = None,
                     max_drops: int = 8) -> tuple[Deformation, list[int], bool]:
    """The level-0 RBF through the feature points PL -> QL (k, 3), the indices of those
    left out because the surface P, F folded through itself with them, and whether the
    result is free of crossings (edges: mesh_edges(F), query: a MeshQuery of F to reuse,
    when already built).

    Feature points that almost coincide on the template but not on the scan (the inner lip
    contour of a face scanned with the mouth open, closed eyelids over open ones) ask the
    interpolant for a huge local stretch: the lips cross. While the fitted surface crosses
    itself, the feature point nearest to the crossings, among those whose displacement
    differs most from their neighbours', is dropped and the RBF fitted again. An edge that
    lies along a seam of its face (the mouth pouch's walls, joined edge on edge) passes
    through it by rounding alone and does not count (untangle.along_seams). The later
    levels are untangled against this result, seam crossings included, and the head's
    check counts every crossing: taken as safe instead, the template itself left meshmonk's
    face with two crossing pairs its fit had cleared.
    """
    dropped: list[int] = []
    keep = np.arange(len(PL))
    for _ in range(max_drops + 1):
        deformation = Deformation(rbf_weights(PL[keep], QL[keep] - PL[keep], kernel, rho=rho))
        X = deformation(P)
        crossing, through = edge_crossings(X, F, edges, query)
        crossing = crossing[~along_seams(P, F, crossing, through)]
        if len(crossing) == 0 or len(keep) <= 4:
            break
        at = X[crossing].mean(axis=1).mean(axis=0)
        near = np.argsort(np.linalg.norm(deformation(PL[keep]) - at, axis=1))[:4]
        D = QL[keep] - PL[keep]
        from scipy.spatial import cKDTree

        _, nb = cKDTree(PL[keep]).query(PL[keep][near], k=min(5, len(keep)))
        odd = np.linalg.norm(D[near] - D[nb[:, 1:]].mean(axis=1), axis=1)
        worst = int(keep[near[int(np.argmax(odd))]])
        dropped.append(worst)
        keep = keep[keep != worst]
    return deformation, sorted(dropped), len(crossing) == 0


def consistent_pairs(X: np.ndarray, Q: np.ndarray, factor: float = 4.0, floor: float = 0.002) -> np.ndarray:
    """(p,) bool: pairs whose residual |Q - X| (X: where the current deformation puts the
    template points, (p, 3) metres) is within `factor` times the median residual (at least
    `floor` metres). A pair far beyond the others matched the wrong sheet of the scan (the
    other lip, behind the ear) and would fold the surface."""
    r = np.linalg.norm(np.asarray(Q) - np.asarray(X), axis=1)
    if len(r) == 0:
        return np.zeros(0, dtype=bool)
    return r <= max(factor * float(np.median(r)), floor)


def _nearest(P: np.ndarray, L: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree
    return cKDTree(P).query(L)[1]
