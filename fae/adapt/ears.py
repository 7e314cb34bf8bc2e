"""The ears of a scan, found by their shape, so the fit can place the template's there.

    ear_pairs(template, scan) -> ((faces (k,), bary (k, 3), points (k, 3)) or None, report)

No face-landmark model sees ears; a template ear two centimetres off the scan's is pulled
by its lower half onto the scan and left standing by its upper half (an elongated ear in
every profile). An ear is what stands out of the side of the head: per side, the surface
near the template's ear (within EAR_SEARCH metres of its centre, in the face frame, both
the template's skin and the scan) is fitted by a smooth height field (|x| as a quadratic
in y and z, refitted to the points within SIDE_KEEP of it), and the points standing out
more than EAR_HEIGHT are the ear. The template's ear points are carried onto the scan's by
trimmed similarity ICP; a result with an implausible scale, turn or residual is dropped.
Template ear vertices mapped that way, put onto the scan, become corresponding points
for the fit (fae.adapt.nonrigid), which weighs them like feature points: they place the
ear in the stiff stages and let the scan give its detail after.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fae.adapt.calibration import similarity_icp
from fae.adapt.errors import Surface
from fae.io.facemodel import FaceModel

EAR_SEARCH = 0.045  # m around the template ear's centre
SIDE_KEEP = 0.003  # m: points this close to the side's height field define it
EAR_HEIGHT = 0.004  # m: points standing out of the side more than this are ear
MIN_EAR_POINTS = 30
SCALE_RANGE = (0.6, 1.5)  # of the template's ear
MAX_TURN = 35.0  # degrees
MAX_RESIDUAL = 0.0025  # m, trimmed RMS of the ICP
PAIRS_PER_EAR = 40
PROJECT_REACH = 0.005  # m: a mapped ear point is put onto the scan when this close


def standing_out(X: np.ndarray, side: float) -> np.ndarray:
    """(n,) metres each point X (n, 3) stands out of a smooth side of the head (|x| as a
    quadratic in y and z, robustly fitted): side +1 for the left (+x), -1 for the right."""
    A = np.c_[np.ones(len(X)), X[:, 1], X[:, 2], X[:, 1] ** 2, X[:, 1] * X[:, 2], X[:, 2] ** 2]
    lateral = side * X[:, 0]
    keep = np.ones(len(X), dtype=bool)
    residual = np.zeros(len(X))
    for _ in range(6):
        if keep.sum() < 6:
            break
        coef, *_ = np.linalg.lstsq(A[keep], lateral[keep], rcond=None)
        residual = lateral - A @ coef
        keep = residual < SIDE_KEEP
    return residual


def ear_pairs(template: FaceModel, scan: Surface) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, dict]:
    """Corresponding points on the template's ears and the scan's (scan in the face frame
    at the template's size, head part only). Returns (faces (k,), bary (k, 3), points
    (k, 3) metres) or None when no ear was found, and a report per ear."""
    P = np.asarray(template.skin_vertices, dtype=np.float64)
    F = np.asarray(template.skin_faces, dtype=np.int64)
    region = np.asarray(template.skin_region)
    # a triangle holding each vertex, and the vertex's corner in it
    corner_face = np.full(len(P), -1, dtype=np.int64)
    corner = np.zeros(len(P), dtype=np.int64)
    for k in range(3):
        corner_face[F[:, k]] = np.arange(len(F))
        corner[F[:, k]] = k
    faces, bary, points, report = [], [], [], {}
    for name, side in (("ear_l", 1.0), ("ear_r", -1.0)):
        if name not in template.region_names:
            continue
        ear = region == template.region_names.index(name)
        if not ear.any():
            continue
        centre = P[ear].mean(axis=0)
        near_t = np.flatnonzero(np.linalg.norm(P - centre, axis=1) < EAR_SEARCH)
        near_s = np.flatnonzero(np.linalg.norm(scan.V - centre, axis=1) < EAR_SEARCH)
        if len(near_s) < MIN_EAR_POINTS:
            report[name] = {"found": False, "why": "no scan near the template's ear"}
            continue
        t_ear = near_t[(standing_out(P[near_t], side) > EAR_HEIGHT) & ear[near_t]]
        s_ear = near_s[standing_out(scan.V[near_s], side) > EAR_HEIGHT]
        if len(s_ear) < MIN_EAR_POINTS or len(t_ear) < MIN_EAR_POINTS:
            report[name] = {"found": False, "why": f"{len(s_ear)} scan points stand out where the ear should be"}
            continue
        A, B = P[t_ear], scan.V[s_ear]
        # scan -> template: hair may hide part of the scan's ear, never part of the template's
        t0 = A.mean(axis=0) - B.mean(axis=0)
        s_inv, R_inv, t_inv, rms = similarity_icp(B, cKDTree(A), A, 1.0, np.eye(3), t0, iterations=30, keep=0.8)
        s, R = 1.0 / s_inv, R_inv.T
        t = -s * R @ t_inv
        turn = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
        entry = {"scan_points": int(len(s_ear)), "scale": float(s), "turn_degrees": turn, "residual_m": rms,
                 "moved_m": float(np.linalg.norm(s * R @ A.mean(axis=0) + t - A.mean(axis=0)))}
        if not (SCALE_RANGE[0] <= s <= SCALE_RANGE[1] and turn <= MAX_TURN and rms <= MAX_RESIDUAL):
            report[name] = {"found": False, "why": "the ear found does not match the template's", **entry}
            continue
        pick = t_ear[np.linspace(0, len(t_ear) - 1, min(PAIRS_PER_EAR, len(t_ear))).astype(int)]
        mapped = s * P[pick] @ R.T + t
        on_scan, _, tri, _ = scan.query.closest_points(mapped, PROJECT_REACH)
        ok = (tri >= 0) & (corner_face[pick] >= 0)
        if ok.sum() < MIN_EAR_POINTS // 3:
            report[name] = {"found": False, "why": "the mapped ear lies off the scan", **entry}
            continue
        b = np.zeros((int(ok.sum()), 3))
        b[np.arange(len(b)), corner[pick[ok]]] = 1.0
        faces.append(corner_face[pick[ok]])
        bary.append(b)
        points.append(on_scan[ok])
        report[name] = {"found": True, "pairs": int(ok.sum()), **entry}
    if not faces:
        return None, report
    return (np.concatenate(faces), np.vstack(bary), np.vstack(points)), report
