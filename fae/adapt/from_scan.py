"""A personalized head from a real scan: the template found in the scan, fitted to its
head part without folds, the anatomy carried over, and the result measured honestly.

    adapt_to_scan(template, scan_V, scan_F, head, pairs=None, landmarks=None) -> (FaceModel, report)

`head` (fae.adapt.head_pose.HeadInScan) says where the head is and which part of the scan
is head; `pairs` are corresponding points found by looking at both faces
(fae.render.landmarks.landmark_pairs, in the face frame); `landmarks` are MPEG-4 feature
points the user gave (scan frame); the ears, which no face-landmark model sees, are found
by their shape (fae.adapt.ears), join them, and are carried to the scan's before the
stiff stages (a marble bust's sit 4.5 cm below where the template's fall). The skin is
fitted by fae.adapt.nonrigid.fit_to_scan, the anatomy carried by
fae.adapt.transfer.personalize (which also moves the hidden skin back behind the visible
skin where the fit pressed it flat), and the errors measured in the
scan's own frame through the head's scan_transform (fae.adapt.errors.scan_fit_errors),
over the face regions' skin that a scanner sees, less the eyelids' rims within EYE_RIM of
an eyeball (a scan shows the eye itself there, and that skin is not fitted to it).

The report's "verdict" lists what makes the head untrustworthy (empty when none): a
folded skin, a face that does not reach its scan. `fae adapt` refuses to write a head with
a verdict (exit status 2).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from fae.adapt.calibration import apply_transform
from fae.adapt.ears import ears_carried, found_ears
from fae.adapt.errors import FACE_REGIONS, scan_fit_errors, surface
from fae.adapt.head_pose import HeadInScan, kept_part
from fae.adapt.nonrigid import fit_to_scan, folded_triangles, start_placement
from fae.adapt.transfer import personalize, visible_skin
from fae.io.facemodel import FaceModel

# Smoothness multiplier per skin region: thin, creased skin bends as a piece; the neck
# follows its scan's shape, not every undercut beneath a bust's jaw (pulled into one, the
# skin under the chin crosses the mandible).
REGION_STIFFNESS = {"eyelid_upper_l": 3.0, "eyelid_upper_r": 3.0, "eyelid_lower_l": 3.0, "eyelid_lower_r": 3.0,
                    "ear_l": 2.0, "ear_r": 2.0, "lip_upper": 1.5, "lip_lower": 1.5, "mouth_cavity": 2.0, "neck": 2.0}
# skin that keeps to its closest compatible scan points (no search along its normal): the
# lips, and the lids near the eyeball, thin folds over the mouth and the eye that would take
# their surface along the normal (on a mask's shut eyes the lids' opening changed and their
# FAPs moved 1.5-1.8x their value; its outer lip corners 0.6x)
NO_RAYS = ("lip_upper", "lip_lower")
NO_RAYS_NEAR_EYE = 0.004  # m
# skin the scan's own points pull in the fit's detail stages: the template's ears are plain
# dishes beside a real ear's rolled rim and deep bowl, and its scalp and neck are smooth
# beside hair and tendons (the busts' scan->skin RMS 0.28-0.32 % -> 0.19-0.29 %; ears were
# half of it). The face is left to its own pairs: pulled too, it lay further off (0.058 -> 0.062 %)
FILL_REGIONS = ("ear_l", "ear_r", "scalp", "neck")
# where the head part's cut crosses a bust's neck above the template's neck end (the neck
# runs into drapery or a plinth there, and the cut is jagged) the scan within NECK_CUT_REACH
# of it is left out of the fit, and the neck stiffens from NECK_STIFF_FROM below the chin
# down to its end (NECK_STIFF_END times its stiffness there), so it keeps a neck's smooth
# shape where a bust's turns into its base (marble_bust's nape: a ledge with teeth along
# the cut, 6 cm above the template's neck end)
NECK_CUT_REACH = 0.01  # m
NECK_CUT_ABOVE_END = 0.01  # m
NECK_STIFF_FROM = 0.02  # m below the chin (2.1)
NECK_STIFF_END = 6.0
EYE_RIM = 0.0025  # m: skin this close to an eyeball follows its neighbours, not the scan
MAX_FACE_RMS_REL = 0.004  # face skin -> scan RMS / head diagonal beyond which the fit failed
MIN_FACE_COVERAGE = 0.8  # share of the face skin within reach of the scan below which it failed


def in_regions(template: FaceModel, names) -> np.ndarray:
    """(n,) bool: skin vertices in any of the regions `names`."""
    idx = [template.region_names.index(r) for r in names if r in template.region_names]
    return np.isin(np.asarray(template.skin_region), idx)


def chin_height(template: FaceModel) -> float:
    """The height (y, metres) of the template's chin, feature point 2.1."""
    return float(template.feature_point_positions()["2.1"][1])


def trimmed_along(V: np.ndarray, F: np.ndarray, edge: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The mesh V (n, 3) metres, F (m, 3) less every face with a corner within `reach`
    metres of a vertex of `edge` (n,) bool: (V' (k, 3), F' (m', 3))."""
    if not np.any(edge):
        return V, F
    near = cKDTree(V[edge]).query(V, distance_upper_bound=reach)[0] < reach
    return kept_part(V, F, ~near)


def neck_cut(template: FaceModel, V: np.ndarray, boundary: np.ndarray) -> np.ndarray:
    """(n,) bool: the boundary vertices (boundary (n,) bool) of a head part V (n, 3), face
    frame, where a bust's neck ran into something else: below the chin and more than
    NECK_CUT_ABOVE_END above the template's neck end (a scan cut there by the template's
    own neck end is neck to its rim)."""
    neck = in_regions(template, ["neck"])
    if not neck.any():
        return np.zeros(len(V), dtype=bool)
    y = np.asarray(V)[:, 1]
    end = float(np.asarray(template.skin_vertices)[neck, 1].min())
    return np.asarray(boundary, dtype=bool) & (y < chin_height(template)) & (y > end + NECK_CUT_ABOVE_END)


def neck_stiffening(template: FaceModel) -> np.ndarray:
    """(n,) multiplier of the skin's smoothness: 1, rising on the neck linearly from
    NECK_STIFF_FROM below the chin to NECK_STIFF_END at the neck's lowest skin."""
    out = np.ones(len(template.skin_vertices))
    neck = in_regions(template, ["neck"])
    if not neck.any():
        return out
    y = np.asarray(template.skin_vertices)[:, 1]
    top = chin_height(template) - NECK_STIFF_FROM
    t = np.clip((top - y[neck]) / max(top - y[neck].min(), 1e-6), 0.0, 1.0)
    out[neck] = 1.0 + (NECK_STIFF_END - 1.0) * t
    return out


def near_eyeballs(template: FaceModel, reach: float) -> np.ndarray:
    """(n,) bool: skin vertices within `reach` metres of an eyeball."""
    from fae.adapt.query import MeshQuery

    near = np.zeros(len(template.skin_vertices), dtype=bool)
    for name in ("eye_l", "eye_r"):
        if name in template.parts:
            V, F = template.mesh(name)
            near |= np.isfinite(MeshQuery(V, F).closest_points(template.skin_vertices, reach)[1])
    return near


def adapt_to_scan(template: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray, head: HeadInScan,
                  pairs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                  landmarks: dict[str, np.ndarray] | None = None) -> tuple[FaceModel, dict]:
    """A personalized copy of `template` fitted to the head part of a scan (V (n, 3), F (m, 3)
    in its own frame and unit). pairs: (template skin faces (k,), bary (k, 3), scan points
    (k, 3) in the face frame); landmarks: FDP name -> (3,) in the scan's frame."""
    t0 = time.perf_counter()
    T = head.transform
    part_V, part_F = kept_part(apply_transform(T, scan_V), scan_F, head.keep)
    if len(part_F) < 100:
        raise ValueError(f"the head part of the scan has {len(part_F)} triangles: too few to fit")
    scan = surface(part_V, part_F)
    # the fit leaves out the scan beside the head part's lower cut (errors still count it)
    fit_scan = surface(*trimmed_along(part_V, part_F, neck_cut(template, part_V, scan.boundary), NECK_CUT_REACH))
    P, F = template.skin_vertices, np.asarray(template.skin_faces, dtype=np.int64)
    # skin a scanner sees, less the lids' rims over the eyeballs: a scan shows the eye
    # itself there (sculpted, or shut), and pulling the rims onto it closes the socket
    seen = visible_skin(template) & ~near_eyeballs(template, EYE_RIM)
    faces, bary, points = [], [], []
    if pairs is not None and len(pairs[0]):
        faces.append(np.asarray(pairs[0], np.int64))
        bary.append(np.asarray(pairs[1], np.float64))
        points.append(np.asarray(pairs[2], np.float64))
    used_landmarks = []
    for name, q in (landmarks or {}).items():
        fp = template.feature_points.get(name)
        if fp is None or fp.part != "skin" or not np.all(np.isfinite(q)):
            continue
        faces.append(np.array([fp.triangle]))
        bary.append(np.asarray(fp.bary, np.float64)[None])
        points.append(apply_transform(T, np.asarray(q, np.float64)[None]))
        used_landmarks.append(name)
    # no face-landmark model sees ears; on a scan of part of the head its rim may stand out like
    # one. Part of the head or not: as the fit's start decides it, from the face's points
    start_map, partial = start_placement(np.asarray(P, np.float64), F, fit_scan, seen,
                                         (np.concatenate(faces), np.vstack(bary), np.vstack(points)) if faces else None)
    ears, ear_report = found_ears(template, scan, partial, start_map)
    face_rows = sum(len(f) for f in faces)
    for ear in ears:
        faces.append(ear.faces)
        bary.append(ear.bary)
        points.append(ear.points)
    lm = (np.concatenate(faces), np.vstack(bary), np.vstack(points)) if faces else None
    # both ears found help place the fit's start (they fix its pitch and scale from behind
    # the face); one alone would turn it, and the face would pay. The skin of an ear found
    # is placed by its pairs, not pulled to the scan nearest it (scalp, when the ear sits
    # centimetres away), until the detail stages.
    start, placed = None, np.zeros(len(P), dtype=bool)
    if lm is not None:
        start = np.ones(len(lm[0]))
        start[face_rows:] = 1.0 if len(ears) == 2 else 0.0
        for ear in ears:
            placed[ear.vertices] = True
    stiffness = np.ones(len(P))
    for region, k in REGION_STIFFNESS.items():
        stiffness[in_regions(template, [region])] = k
    stiffness *= neck_stiffening(template)
    fit = fit_to_scan(P, F, fit_scan, seen, landmarks=lm, stiffness=stiffness,
                      rays=~in_regions(template, NO_RAYS) & ~near_eyeballs(template, NO_RAYS_NEAR_EYE), start=start,
                      placed=placed,
                      carry=(lambda X: ears_carried(P, X, ears)) if ears else None,
                      fill=in_regions(template, FILL_REGIONS))
    t_fit = time.perf_counter() - t0
    model, report = personalize(template, fit.vertices, T, head.unit, "surface")
    # the errors, in the scan's own frame through the head's scan_transform (no refit)
    S = model.scan_transform
    face = in_regions(template, FACE_REGIONS) & seen
    errors = scan_fit_errors(apply_transform(S, model.skin_vertices), model.skin_faces, face,
                             apply_transform(np.linalg.inv(T), part_V), part_F, neck=in_regions(template, ["neck"]))
    errors["face_vertices_scored"] = int(face.sum())  # the lids' rims over the eyeballs are not
    # the fit's folds, on the template's faces: a cap flipped since (fitted_caps_flipped) is a
    # face the template does not have, which may lie reversed on it; the flip folds nothing
    visible_faces = seen[F].all(axis=1)
    folded = folded_triangles(P, model.skin_vertices, F)
    verdict = []
    if folded[visible_faces].any():
        verdict.append(f"{int(folded[visible_faces].sum())} visible skin triangles folded")
    if errors["face_to_scan_rms_rel"] > MAX_FACE_RMS_REL:
        verdict.append(f"the face lies {errors['face_to_scan_rms_rel'] * 100:.2f} % of the head's diagonal from "
                       f"the scan (RMS; at most {MAX_FACE_RMS_REL * 100:.2f} % expected)")
    if errors["face_coverage"] < MIN_FACE_COVERAGE:
        verdict.append(f"only {errors['face_coverage'] * 100:.0f} % of the face reaches the scan "
                       f"(at least {MIN_FACE_COVERAGE * 100:.0f} % expected)")
    report.update({
        "head_part": head.report(scan_V),
        "feature_pairs": 0 if lm is None else int(len(lm[0])),
        "landmarks_used": used_landmarks,
        "ears": ear_report,
        "errors": errors,
        "folded_triangles": {"visible": int(folded[visible_faces].sum()), "all": int(folded.sum())},
        "scan_covers_part_of_head": fit.partial_scan,
        "fit_stages": fit.stages,
        "fit_seconds": t_fit,
        "seconds": time.perf_counter() - t0,
        "verdict": verdict,
    })
    return model, report
