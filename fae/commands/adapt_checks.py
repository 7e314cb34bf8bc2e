"""What `fae adapt` refuses: inputs it cannot fit, and fits no one should animate.

Each check returns a one-line reason (naming the file or the measure, and what was
expected) or nothing; the command prints it and exits 2.

Inputs (before any work): a scan with too few triangles that have an area (one triangle,
degenerate triangles, a flat or collapsed mesh), faces naming vertices that do not exist;
feature points that do not lie on the scan (another unit or frame: metres for a scan in
mm), or with too few of them. Outputs that would overwrite an input.

Fits (after the work, before anything is written): errors that are not finite (part of
the model found no scan at all), an anatomy transfer whose scales no head has (eyeballs
scaled far from the face's own scale, or unlike each other; FAPU ratios far from 1).
"""

from __future__ import annotations

import math

import numpy as np

MIN_SCAN_TRIANGLES = 100  # with an area; the head part alone needs this many (fae.adapt.from_scan)
LANDMARK_DISTANCE_SHARE = 0.1  # of the scan's diagonal: the median feature point lies closer to the scan
FAPU_RATIO_RANGE = (0.5, 2.0)  # the fitted face's FAPU over the template's: a head is at most twice another
# An eyeball's scale over the FAPU ratio (eyes grow with faces). The menpo3d face fits with
# 0.60 (its sockets are shallow and the eyeballs are shrunk into them); 8,492 and 0.45 came
# from scans with most of their faces missing or with noisy feature points.
EYE_TO_FACE_RANGE = (0.5, 1.8)
EYES_APART = 1.25  # the larger eyeball's scale over the smaller one's
# A scan whose area faces into it more than out (fae.anatomy.checks.outward_share below
# this) is wound inside out, as exporters and mirroring leave scans: the busts 0.87-0.93,
# face masks 0.98-1.0, the front half of a bust 0.76; the same turned 0.002-0.25
SCAN_INSIDE_OUT_SHARE = 0.4
# ... and one above that but below this faces in and out about equally, with no winding to
# turn: a scan doubled back to back (0.5) fitted half its faces against the others, a head
# with the hair flattened, eyes and mouth misshapen and a lump on the neck
SCAN_MIXED_SHARE = 0.65
# a head in micrometres 1,000 km from the origin; far beyond any unit (1e200) numpy warned in
# eight lines of overflows and the scan was said to have "0 triangles with an area"
MAX_COORDINATE = 1e12


def scan_problem(V: np.ndarray, F: np.ndarray, path: str) -> str | None:
    """Why the mesh (V, F) of `path` cannot be a head scan, or None."""
    with np.errstate(over="ignore", invalid="ignore"):
        diagonal = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    if not np.isfinite(diagonal) or np.abs(V).max() > MAX_COORDINATE:  # numpy's overflow warnings, then "0 triangles"
        return (f"{path}: coordinates up to {np.abs(V).max():.3g}; expected a head scan in some unit of length "
                f"(at most {MAX_COORDINATE:.0e} from the origin)")
    if not diagonal > 0:
        return f"{path}: every vertex is at one point; expected a head scan's surface"
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    real = int((area > 1e-12 * diagonal * diagonal).sum())
    if real < MIN_SCAN_TRIANGLES:
        return (f"{path}: {real} of its {len(F)} triangles have an area; expected a head scan's surface of at "
                f"least {MIN_SCAN_TRIANGLES}")
    extent = V.max(axis=0) - V.min(axis=0)
    if extent.min() < 1e-6 * diagonal:
        return f"{path}: the mesh is flat (it lies in a plane); expected a head scan's surface"
    return None


def scan_outward(V: np.ndarray, F: np.ndarray, path: str, say) -> tuple[np.ndarray, bool]:
    """(F, turned): the scan's faces, turned outward (each triangle's corners reversed) when
    they are wound inside out, with a notice to `say`: the fit pairs by normals and found
    no face on the turned marble bust ("only 77 % of the face reaches the scan"). Raises
    ValueError naming the file when about as much of its area faces in as out."""
    from fae.anatomy.checks import outward_share

    share = outward_share(V, F)
    if SCAN_INSIDE_OUT_SHARE <= share < SCAN_MIXED_SHARE:
        raise ValueError(f"{path}: {(1 - share) * 100:.0f} % of its area faces into it (faces wound against their "
                         "neighbours, or the surface doubled back to back); expected one outward winding (a mesh "
                         "tool's 're-orient faces coherently' mends it)")
    if share >= SCAN_INSIDE_OUT_SHARE:
        return F, False
    say(f"{path}: its faces are wound inside out ({(1 - share) * 100:.0f} % of its area faces inward); "
        "turned outward")
    return np.ascontiguousarray(F[:, ::-1]), True


def landmark_problem(V: np.ndarray, landmarks: dict[str, np.ndarray], path: str, scan: str) -> str | None:
    """Why the feature points of `path` do not belong to the scan (V of `scan`), or None."""
    from scipy.spatial import cKDTree

    if not landmarks:
        return f"{path}: no feature points; expected MPEG-4 names (\"9.3\") or 68 iBUG points"
    points = np.array(list(landmarks.values()), dtype=np.float64)
    diagonal = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    distance = float(np.median(cKDTree(V).query(points)[0]))
    if distance <= LANDMARK_DISTANCE_SHARE * diagonal:
        return None
    spread = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return (f"{path}: the feature points lie {distance:.4g} units from {scan} (median; the scan is {diagonal:.4g} "
            f"across, the points {spread:.4g}); expected points on the scan, in its unit and frame (metres or cm "
            "for a scan in mm?)")


def _non_finite(values: dict, where: str) -> list[str]:
    bad = [k for k, v in values.items() if isinstance(v, (float, np.floating)) and not math.isfinite(v)]
    return [f"{where} {', '.join(bad)} not finite (part of the model found no scan)"] if bad else []


def implausible_fit(report: dict) -> list[str]:
    """Reasons the fitted head is not to be trusted, from the fit's report (empty: none)."""
    reasons = []
    for key in ("errors", "final"):
        if isinstance(report.get(key), dict):
            reasons += _non_finite(report[key], "fit error" if key == "errors" else "final error")
    ratio = report.get("fapu_ratio")
    if ratio is not None:
        low, high = FAPU_RATIO_RANGE
        if not (math.isfinite(ratio) and low <= ratio <= high):
            reasons.append(f"the face's FAPU are {ratio:.3g} times the template's (expected {low:g}..{high:g})")
            ratio = None
    eyes = {k: v for k, v in (report.get("eye_scale") or {}).items()}
    if eyes:
        scales = np.array(list(eyes.values()), dtype=np.float64)
        if not np.all(np.isfinite(scales)) or scales.min() <= 0:
            reasons.append(f"eyeball scales {_shown(eyes)} are not positive numbers")
        else:
            if ratio is not None:
                low, high = EYE_TO_FACE_RANGE
                for name, s in eyes.items():
                    if not low <= s / ratio <= high:
                        reasons.append(f"{name} is scaled {s:.3g}, {s / ratio:.3g} times the face's own scale "
                                       f"{ratio:.3g} (expected {low:g}..{high:g} times)")
            if scales.max() > EYES_APART * scales.min():
                reasons.append(f"the eyeballs are scaled unlike each other ({_shown(eyes)}; at most "
                               f"{EYES_APART:g} times apart expected)")
    return reasons


def _shown(scales: dict) -> str:
    return ", ".join(f"{k} {v:.3g}" for k, v in scales.items())
