"""Fitting errors (paper 000 §5; symmetric RMS distances as in paper 001's tables).

Distances are point-to-surface (closest point on the triangles, Warp BVH). A model vertex
is compatible with its closest scan point when their normals are at most 90 degrees apart
and the distance is within `max_distance` (paper 000: 1/10 of the template's width); the
closest point must not lie on a face touching the scan's boundary (so holes and cropped
edges do not count as matches). Incompatible vertices get weight 0 (eq. 22).

distance_error = sqrt(sum w_i d_i^2 / sum w_i) over compatible vertices (the root of eq. 22,
normalized by the weights so that matching fewer vertices cannot lower it), metres;
marker_error = RMS distance between corresponding markers (root-mean of eq. 23), metres;
combined_error = distance_error + 0.1 marker_error (eq. 24 with alpha = 1, beta = 0.1, the
weights that reproduce paper 000's table 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fae.adapt.geometry import boundary_vertices, per_vertex_normals
from fae.adapt.query import MeshQuery

MARKER_WEIGHT = 0.1


@dataclass
class Surface:
    """A mesh prepared for queries: V (n, 3) metres, F (m, 3), N (n, 3) vertex normals,
    boundary (n,) bool, face_on_boundary (m,) bool, tree (KD-tree of V), query (BVH),
    diagonal (bounding-box diagonal, metres)."""

    V: np.ndarray
    F: np.ndarray
    N: np.ndarray
    boundary: np.ndarray
    face_on_boundary: np.ndarray
    tree: cKDTree
    query: MeshQuery
    diagonal: float


def surface(V: np.ndarray, F: np.ndarray, query: MeshQuery | None = None) -> Surface:
    """Prepare mesh V (n, 3), F (m, 3) for closest-point and ray queries. query: a
    MeshQuery of the same faces to reuse (moved to V: a refit, not a rebuild)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    if query is None:
        query = MeshQuery(V, F)
    else:
        query.move(V)
    b = boundary_vertices(F, len(V))
    return Surface(V, F, per_vertex_normals(V, F), b, b[F].any(axis=1), cKDTree(V, balanced_tree=False),
                   query, float(np.linalg.norm(np.ptp(V, axis=0))))


def compatible_closest_points(X: np.ndarray, NX: np.ndarray, target: Surface, max_distance: float
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest points on `target` to X (n, 3) with normals NX (n, 3).

    Returns points (n, 3), normals (n, 3) there, distance (n,), compatible (n,) bool.
    """
    pts, dist, face, bary = target.query.closest_points(X, max_distance)
    ok = face >= 0
    N = np.zeros_like(pts)
    N[ok] = np.einsum("nk,nkd->nd", bary[ok], target.N[target.F[face[ok]]])
    ok &= np.sum(N * NX, 1) > 0.0
    ok[ok] &= ~target.face_on_boundary[face[ok]]
    return pts, N, dist, ok


def distance_error(dist: np.ndarray, weights: np.ndarray) -> float:
    """sqrt(sum w d^2 / sum w), metres; inf when nothing is compatible."""
    w = np.asarray(weights, dtype=np.float64)
    if w.sum() <= 0:
        return float("inf")
    d = np.where(w > 0, dist, 0.0)
    return float(np.sqrt(np.sum(w * d * d) / w.sum()))


def marker_error(U: np.ndarray, V: np.ndarray) -> float:
    """RMS distance (metres) between corresponding markers U, V (k, 3); 0 when k = 0."""
    if len(U) == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.sum((np.asarray(U) - np.asarray(V)) ** 2, axis=1))))


def combined_error(distance: float, marker: float) -> float:
    """distance + 0.1 marker (eq. 24), metres."""
    return float(distance + MARKER_WEIGHT * marker)


def symmetric_rms(model: Surface, scan: Surface, max_distance: float, scored: np.ndarray | None = None,
                  scan_samples: int = 20000, model_match: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> dict[str, float]:
    """RMS closest-point distances both ways over compatible points, metres and / scan diagonal.

    scored (n,) bool: model vertices that count (default all; a head leaves out skin no
    scanner sees); scan_samples: at most this many scan vertices, evenly strided, are used;
    model_match: distance (n,) and compatible (n,) of the model's vertices on the scan when
    already known (compatible_closest_points over the scored ones).
    Returns scan_to_model_rms, model_to_scan_rms, *_rel, and the compatible fractions.
    """
    if model_match is None:
        _, _, d_ms, ok_ms = compatible_closest_points(model.V, model.N, scan, max_distance)
    else:
        d_ms, ok_ms = model_match[0], model_match[1].copy()
    if scored is not None:
        ok_ms &= scored
    step = max(1, len(scan.V) // scan_samples)
    _, _, d_sm, ok_sm = compatible_closest_points(scan.V[::step], scan.N[::step], model, max_distance)
    ms = float(np.sqrt(np.mean(d_ms[ok_ms] ** 2))) if ok_ms.any() else float("inf")
    sm = float(np.sqrt(np.mean(d_sm[ok_sm] ** 2))) if ok_sm.any() else float("inf")
    return {
        "scan_to_model_rms": sm,
        "model_to_scan_rms": ms,
        "scan_to_model_rms_rel": sm / scan.diagonal,
        "model_to_scan_rms_rel": ms / scan.diagonal,
        "scan_covered_fraction": float(ok_sm.mean()),
        "model_matched_fraction": float(ok_ms.mean()),
    }


FACE_REGIONS = ("forehead", "eyelid_upper_l", "eyelid_upper_r", "eyelid_lower_l", "eyelid_lower_r", "nose",
                "cheek_l", "cheek_r", "lip_upper", "lip_lower", "chin", "jaw_l", "jaw_r")
COVER_SHARE = 0.02  # of the head's diagonal: a point farther than this from the other surface is a hole, not an error


def scan_fit_errors(skin_V: np.ndarray, skin_F: np.ndarray, face: np.ndarray, scan_V: np.ndarray,
                    scan_F: np.ndarray, neck: np.ndarray | None = None) -> dict[str, float]:
    """How far an adapted skin lies from the head part of its scan, in the scan's own frame.

    skin_V (n, 3), skin_F: the skin mapped into the scan's frame and unit (through its
    scan_transform, no refit); face (n,) bool: the skin of the face regions (FACE_REGIONS)
    that a scanner sees; scan_V (k, 3), scan_F: the head part of the scan, same frame.
    The diagonal is the head part's bounding-box diagonal. Points whose closest point on
    the other surface lies on a triangle at its boundary (a hole, where the scan or the
    skin ends) or beyond COVER_SHARE of the diagonal have no counterpart there: they are
    left out of the RMS and counted against coverage, which is reported beside each RMS.
    Returns face_to_scan_rms, scan_to_skin_rms (scan units), both also / diagonal
    (*_rel), face_coverage, scan_coverage, diagonal, and scan_to_skin_all_rms(_rel): over
    every scan point but those nearest the skin's open rim, the ones farther than
    COVER_SHARE counted at their distance (the skin covers the whole head, so there a
    point it does not reach is an error of the fit, or scan the head part should not
    hold: a bust's drapery). neck (n,) bool, the skin of the neck:
    with it, head_to_skin_rms(_rel) and head_coverage are the scan_to_skin figures over the
    scan points whose nearest skin vertex is not neck (cranium, face and ears).
    """
    skin_V = np.asarray(skin_V, dtype=np.float64)
    scan_V = np.asarray(scan_V, dtype=np.float64)
    diagonal = float(np.linalg.norm(np.ptp(scan_V, axis=0)))
    reach = COVER_SHARE * diagonal
    def distances(X, V, F, within=reach):
        F = np.asarray(F, dtype=np.int64)
        _, d, tri, _ = MeshQuery(V, F).closest_points(X, within)
        rim = boundary_vertices(F, len(V))[F].any(axis=1)
        return np.where((tri >= 0) & ~rim[np.maximum(tri, 0)], d, np.inf)

    on_scan = distances(skin_V[face], scan_V, scan_F)
    # every scan point's distance (no scan point lies farther from the skin than the
    # diagonal of both together); those within reach are the covered ones
    both = np.vstack([scan_V, skin_V])
    everywhere = distances(scan_V, skin_V, skin_F, within=1.01 * float(np.linalg.norm(np.ptp(both, axis=0))))
    on_skin = np.where(everywhere <= reach, everywhere, np.inf)
    everywhere = everywhere[np.isfinite(everywhere)]
    all_rms = float(np.sqrt(np.mean(everywhere ** 2))) if len(everywhere) else float("inf")
    out = {"diagonal": diagonal, "scan_to_skin_all_rms": all_rms,
           "scan_to_skin_all_rms_rel": all_rms / diagonal if diagonal > 0 else float("inf")}
    figures = [("face_to_scan", on_scan), ("scan_to_skin", on_skin)]
    if neck is not None:  # each scan point belongs where its nearest skin vertex does
        on_neck = np.asarray(neck, dtype=bool)[cKDTree(skin_V).query(scan_V)[1]]
        figures.append(("head_to_skin", on_skin[~on_neck]))
    for key, d in figures:
        hit = np.isfinite(d)
        rms = float(np.sqrt(np.mean(d[hit] ** 2))) if hit.any() else float("inf")
        out[f"{key}_rms"] = rms
        out[f"{key}_rms_rel"] = rms / diagonal if diagonal > 0 else float("inf")
        out[f"{key.split('_to_')[0]}_coverage"] = float(hit.mean()) if len(hit) else 0.0
    return out
