"""A personalized head from a scan, as `fae adapt` makes it (the default "surface" method).

    adapt_scan(template, V, F, face_pairs, landmarks=None, scan_name="scan",
               landmarks_name="--landmarks", say=None) -> (FaceModel, report, keep)

Steps: feature points given are checked against each other (one that disagrees with the
rest is dropped, with a notice), against the scan (one off it is dropped; points off it
as a whole are refused) and, part by part, against the face found on the scan (a part
marked on the wrong feature is dropped, with a notice: part_offsets, misplaced_parts);
the head is found in the scan, from them or from the scan's shape alone
(fae.adapt.head_pose); `face_pairs(part_V, part_F)` finds corresponding
points on the head part (fae adapt passes a face-landmark model looking at the template and
at the head part from the same camera, fae.render.landmarks: a layer above this one); where
no feature points are given and those points say the pose is turned (MAX_PAIRS_TURN) or
sized wrong (MAX_PAIRS_SCALE), they place the head again;
the skin is fitted and the anatomy carried over (fae.adapt.from_scan). The report gains
what the search found and a confidence summary. keep (n,) bool: the scan vertices of the
head part.

Whenever a step cannot be trusted, AdaptRefused says why, naming the scan and what would
help (usually feature points): `fae adapt` prints it and exits with status 2. What the fit
itself measures (folds, a face off the scan) goes into the report's verdict instead, for
the caller to weigh. Notices go to `say` (one line each; default: none).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from fae.anatomy.surface_points import markup_positions
from fae.io.facemodel import FaceModel

# A face found on the scan is trusted with at least this many point pairs, whose RMS
# distance from their best similarity is at most this share of the eye distance (the
# busts: 0.08-0.10; a face mistaken elsewhere on a scan: far above).
MIN_PAIRS = 20
MIN_HEAD_TRIANGLES = 100
MAX_PAIR_RESIDUAL_SHARE = 0.2
MIN_GIVEN_POINTS = 4  # feature points given that place the head (a similarity needs 3, one more to check it)
FEW_GIVEN_POINTS = 12  # fewer feature points given than this, not placing the head on the scan: the search may
# Feature points given lie on the scan they mark: the busts' own (fae adapt's, read back off
# the fitted skin) within 4.4 mm, the menpo3d mask's iBUG-68 within 0.7 mm. A point farther
# than OFF_SCAN (metres, at the template's size) is dropped with a notice; when their
# median lies farther than OFF_SCAN_MEDIAN, or more than OFF_SCAN_SHARE of them are
# dropped, the points belong to another head (or frame, or unit) and nothing is fitted:
# the marble bust's points scaled 1.2x about their middle lay a median 8 mm off it and
# played with a hole in the cheek at rest and the mouth torn open.
OFF_SCAN = 0.01
# a face found this many degrees turned from the head's pose places the head again (the whole
# busts: up to 11 degrees; the wreath's face cut out: 13, and 37 when posed by the face alone)
MAX_PAIRS_TURN = 15.0
# nor sized this many times larger or smaller (the busts' faces 0.87-0.97, the menpo3d mask's
# 1.0-1.08; the meshmonk face, in millimetres, placed by the search at 1/1.56 of its size:
# its unit was taken as none, and its head came out 1.6x life size)
MAX_PAIRS_SCALE = 1.25
OFF_SCAN_MEDIAN = 0.003
OFF_SCAN_SHARE = 0.25
COINCIDENT_SHARE = 0.01  # of the scan's diagonal: feature points spread less lie on one spot


# Feature points given are checked, part by part (the mouth's, an eye's: fae.mpeg4.fdps.face_part),
# against the face the face-landmark model finds on the scan (misplaced_parts). A marker can
# place a whole part on the wrong feature (the menpo3d mask's mouth moved 3.2 cm down onto
# its chin, along the surface): each point agrees with its own part, the scan holds them
# all, and the fit laid the template's mouth on the chin (face to scan 0.088 % of the
# diagonal, nothing folded: trusted). The found face's pairs within PART_PAIR_REACH of a
# given point's place on the template say where the scan has it: the mask's own iBUG-68
# points lie a median of 3-11 mm from it, part by part (its right brow 11 mm), the moved
# mouth 29 mm. A part farther than GIVEN_PART_OFF of the template's eye distance and
# PART_OUTLIER times the other parts' median is left out, with a notice; when half the
# parts or more lie that far, the found face is doubted instead, and the points kept. The
# jaw is not judged: its points follow conventions that differ (iBUG's jaw line against
# MPEG-4's chin corners: the mask's 2.12 lies 17 mm from the found face's).
GIVEN_PART_OFF = 0.25
PART_OUTLIER = 3.0
UNJUDGED_PARTS = ("jaw",)
PART_WORDS = {"mouth": "mouth", "nose": "nose", "jaw": "jaw", "head": "head", "eye_l": "left eye",
              "eye_r": "right eye", "brow_l": "left brow", "brow_r": "right brow", "cheek_l": "left cheek",
              "cheek_r": "right cheek", "ear_l": "left ear", "ear_r": "right ear"}
PART_PAIR_REACH = 0.012  # m


def part_offsets(template: FaceModel, given: dict[str, np.ndarray], skin_points: np.ndarray,
                 scan_points: np.ndarray) -> dict[str, tuple[list[str], float]]:
    """Per part of the face (fae.mpeg4.fdps.face_part), the names of the feature points
    given (face frame, metres) and the median distance (metres) of those with found pairs
    near them from where the pairs (template skin points (k, 3) -> scan points (k, 3), face
    frame) put them: each point's place on the template moved by the pairs' mean motion
    within PART_PAIR_REACH (weighted by nearness; a point with fewer than two pairs there
    has no say). Parts with fewer than two points that have a say are left out."""
    from scipy.spatial import cKDTree

    from fae.mpeg4.fdps import face_part

    fdp = markup_positions(template)
    S = np.asarray(skin_points, dtype=np.float64)
    Q = np.asarray(scan_points, dtype=np.float64)
    tree = cKDTree(S)
    names: dict[str, list[str]] = {}
    offsets: dict[str, list[float]] = {}
    for n, g in given.items():
        part = face_part(n) if n in fdp else None
        if part is None:
            continue
        names.setdefault(part, []).append(n)
        near = np.asarray(tree.query_ball_point(fdp[n], PART_PAIR_REACH), dtype=np.int64)
        if len(near) < 2:
            continue
        w = 1.0 / (np.linalg.norm(S[near] - fdp[n], axis=1) + 1e-3)
        found = fdp[n] + (w[:, None] * (Q[near] - S[near])).sum(axis=0) / w.sum()
        offsets.setdefault(part, []).append(float(np.linalg.norm(np.asarray(g, np.float64) - found)))
    return {part: (names[part], float(np.median(d))) for part, d in offsets.items() if len(d) >= 2}


def misplaced_parts(offsets: dict[str, tuple[list[str], float]], limit: float
                    ) -> tuple[dict[str, tuple[list[str], float]], bool]:
    """(the parts of `offsets` (part_offsets) to leave out, whether the found face is in
    doubt): a part is left out when its distance exceeds `limit` (metres) and PART_OUTLIER
    times the median of the other judged parts'; when half of the judged parts or more
    exceed `limit`, none is left out and the found face is in doubt. UNJUDGED_PARTS are
    not judged."""
    judged = {p: v for p, v in offsets.items() if p not in UNJUDGED_PARTS}
    over = {p: v for p, v in judged.items() if v[1] > limit}
    if not over:
        return {}, False
    if 2 * len(over) >= len(judged):
        return {}, True
    return {p: v for p, v in over.items()
            if v[1] > PART_OUTLIER * float(np.median([w[1] for q, w in judged.items() if q != p]))}, False


class AdaptRefused(Exception):
    """The scan cannot be adapted well enough; the message says why and what would help."""


class FacePairsUnavailable(Exception):
    """face_pairs cannot look at the scan: fatal (nothing to draw with) or not (no
    face-landmark model: feature points given can stand in for it)."""

    def __init__(self, message: str, fatal: bool):
        super().__init__(message)
        self.fatal = fatal


def eye_distance(template: FaceModel) -> float:
    """The template's pupil distance (ES0), metres."""
    fdp = template.feature_point_positions()
    return float(np.linalg.norm(fdp["3.5"] - fdp["3.6"])) if "3.5" in fdp and "3.6" in fdp else 0.065


def _on_scan(V: np.ndarray, F: np.ndarray, scale: float, landmarks: dict[str, np.ndarray], scan_name: str,
             landmarks_name: str, say: Callable[[str], None]) -> list[str]:
    """Names of the feature points given (scan frame and unit) that lie on the scan V (n, 3),
    F (m, 3): within OFF_SCAN of it, with `scale` scan units -> metres; the others are named
    in a notice. Raises AdaptRefused when the points as a whole lie off the scan."""
    from fae.adapt.query import MeshQuery

    names = list(landmarks)  # the distances at the template's size (scale: scan units -> metres as fitted)
    off = MeshQuery(V, F).closest_points(np.array([landmarks[n] for n in names]))[1] * scale
    far = off > OFF_SCAN
    median = float(np.median(off))
    if median > OFF_SCAN_MEDIAN or far.mean() > OFF_SCAN_SHARE:
        raise AdaptRefused(
            f"{landmarks_name}: the feature points lie off {scan_name} (median {median * 1000:.1f} mm at the "
            f"template's size, {int(far.sum())} of {len(names)} farther than {OFF_SCAN * 1000:.0f} mm; at most "
            f"{OFF_SCAN_MEDIAN * 1000:.0f} mm and {OFF_SCAN_SHARE * 100:.0f} % expected): do they belong to this "
            "mesh, in its frame and unit?")
    for n, d in zip(names, off):
        if d > OFF_SCAN:
            say(f"ignored feature point {n}: {d * 1000:.0f} mm off {scan_name} at the template's size "
                "(wrong placement?)")
    return [n for n, d in zip(names, off) if d <= OFF_SCAN]


def adapt_scan(template: FaceModel, V: np.ndarray, F: np.ndarray, face_pairs: Callable,
               landmarks: dict[str, np.ndarray] | None = None, scan_name: str = "scan",
               landmarks_name: str = "--landmarks",
               say: Callable[[str], None] | None = None,
               landmark_mesh: tuple[np.ndarray, np.ndarray] | None = None,
               search_with_landmarks: bool = False) -> tuple[FaceModel, dict, np.ndarray]:
    """See the module docstring. V (n, 3), F (m, 3): the scan in its own frame and unit;
    face_pairs(part_V, part_F): an object with face (k,), bary (k, 3), scan_points (k, 3)
    and report (with "similarity_residual_m"), or None; raises FacePairsUnavailable;
    landmarks: FDP name -> (3,) in the scan's frame; scan_name / landmarks_name: how
    messages name the two inputs; landmark_mesh: (V, F) the feature points must lie on
    (default the scan; motion transfer fits only a mesh's skin pieces, and a point may
    lie on a separate ear); search_with_landmarks: with fewer than FEW_GIVEN_POINTS feature
    points given, the head is also searched for as without them, and that placement is kept
    where theirs does not lie on the scan (not trusted: face coverage, residual) while the
    search's does and places the same head (head_pose.poses_agree); the points still pull
    the fit. The marble bust's seven midline points placed it 25 degrees turned and off the
    scan (face coverage 31 %, 11.5 mm), and its head came out further from the scan than
    with none (scan->skin 0.27 % of its diagonal without the neck, face 0.060 %; with none
    0.16 %, 0.044 %); from the search's placement 0.159 %, 0.043 %. Where their placement
    lies on the scan it stays: a search over a face alone can be turned 30-40 degrees (the
    menpo3d mask with ten of its points: face 0.059 % from theirs, 0.128 % from the
    search's). Not mended: five well-spread points place the marble on the scan yet 11
    degrees off (0.26 %). Many points place a head as well as the search or better: the
    busts' 72 the same to the digit; the menpo3d mask's 68 (face 0.066 % from theirs,
    0.115 % from the search's)."""
    from fae.adapt.calibration import apply_transform, outlier_landmarks, similarity_transform
    from fae.adapt.from_scan import adapt_to_scan
    from fae.adapt.head_pose import (MAX_HEAD_RESIDUAL, MIN_FACE_COVERAGE, find_head, head_from_landmarks, kept_part,
                                     other_poses, poses_agree)

    say = say or (lambda msg: None)
    pose_source = "feature points given" if landmarks else "searched"
    searched = None  # with feature points given: the head as found without them (search_with_landmarks)

    def placed_by(points: dict[str, np.ndarray]):
        """The head placed by feature points given (name -> (3,) scan frame), or the one
        searched for where the two agree."""
        nonlocal pose_source
        fdp = markup_positions(template)
        by_points = head_from_landmarks(template, V, F, np.array([fdp[n] for n in points]),
                                        np.array([points[n] for n in points]))
        if searched is not None and searched.trusted and searched.heads == 1 and not by_points.trusted \
                and poses_agree(searched, by_points):
            pose_source = "searched (the feature points given agree, but do not place it on the scan)"
            return searched
        pose_source = "feature points given"
        return by_points

    try:
        if landmarks:
            fdp = markup_positions(template)
            names = [n for n in landmarks if n in fdp and template.feature_points[n].part == "skin"
                     and np.all(np.isfinite(landmarks[n]))]
            if len(names) < MIN_GIVEN_POINTS:
                raise AdaptRefused(f"{landmarks_name}: {len(names)} usable feature points of the template's skin; at "
                                   f"least {MIN_GIVEN_POINTS} are needed (or leave --landmarks out to find the head "
                                   "without them)")
            A = np.array([fdp[n] for n in names])
            B = np.array([landmarks[n] for n in names])
            extent, diagonal = float(np.ptp(B, axis=0).max()), float(np.linalg.norm(np.ptp(V, axis=0)))
            if extent <= COINCIDENT_SHARE * diagonal:  # no pose to take from them (the fit's numbers were absurd)
                raise AdaptRefused(f"{landmarks_name}: the {len(names)} feature points lie within {extent:.3g} units "
                                   f"of each other, {scan_name} {diagonal:.4g} across; expected each at its own "
                                   "place on the face")
            wrong = set(outlier_landmarks(B, A, names))
            for n in sorted(wrong):
                say(f"ignored feature point {n}: disagrees with the others (wrong placement?)")
            names = [n for n in names if n not in wrong]
            landmarks = {n: landmarks[n] for n in names}
            if search_with_landmarks and len(landmarks) < FEW_GIVEN_POINTS:
                searched = find_head(template, V, F)
            head = placed_by(landmarks)
            names = _on_scan(*(landmark_mesh or (V, F)), head.scale, landmarks, scan_name, landmarks_name, say)
            if len(names) < MIN_GIVEN_POINTS:
                raise AdaptRefused(f"{landmarks_name}: {len(names)} feature points lie on {scan_name}; at least "
                                   f"{MIN_GIVEN_POINTS} are needed")
            if len(names) < len(landmarks):
                landmarks = {n: landmarks[n] for n in names}
                head = placed_by(landmarks)
        else:
            head = find_head(template, V, F)
            if not head.trusted:
                raise AdaptRefused(
                    f"{scan_name}: could not find a head that matches the template (face covered "
                    f"{head.face_coverage * 100:.0f} %, at least {MIN_FACE_COVERAGE * 100:.0f} % needed; "
                    f"residual {head.residual * 1000:.1f} mm, at most {MAX_HEAD_RESIDUAL * 1000:.0f} mm); "
                    "give feature points with --landmarks")
            if head.heads > 1:
                lo, hi = V[head.keep].min(axis=0), V[head.keep].max(axis=0)
                say(f"{scan_name}: {head.heads} heads found in the scan; fitting the one whose face lies closest "
                    f"to the template's, between {np.round(lo, 3).tolist()} and {np.round(hi, 3).tolist()} "
                    "(cut the scan to the head you want, or give its feature points with --landmarks)")

        def looked_at(head):
            """The head part of the scan in the face frame and the feature pairs found on it."""
            part_V, part_F = kept_part(apply_transform(head.transform, V), F, head.keep)
            if len(part_F) < MIN_HEAD_TRIANGLES:
                raise AdaptRefused(
                    f"{scan_name}: the part of the scan where the head should be holds {len(part_F)} triangles "
                    f"(at least {MIN_HEAD_TRIANGLES} expected): "
                    + ("do the feature points belong to this scan, in its unit?" if landmarks
                       else "give feature points with --landmarks"))
            try:
                return face_pairs(part_V, part_F)
            except FacePairsUnavailable as exc:
                if exc.fatal or not landmarks:
                    raise AdaptRefused(str(exc)) from exc
                return None

        def skin_points(found) -> np.ndarray:
            """(k, 3) the template's skin points of the pairs, metres."""
            P = np.asarray(template.skin_vertices, np.float64)
            T = P[np.asarray(template.skin_faces, np.int64)[found.face]]
            return np.einsum("kj,kjd->kd", found.bary, T)

        def pairs_turn(found) -> tuple[float, float]:
            """Degrees the pairs' similarity turns the template's face to the scan's (face frame),
            and how many times it scales it."""
            scale, R, _ = similarity_transform(skin_points(found), found.scan_points)
            return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))), float(scale)

        def pairs_off(found) -> tuple[float, float]:
            """(turn in degrees, factor the size is off by) of the face found (pairs_turn)."""
            turn, scale = pairs_turn(found)
            return turn, float(np.exp(abs(np.log(scale))))

        def usable(found) -> bool:
            return found is not None and len(found.face) >= MIN_PAIRS and \
                found.report["similarity_residual_m"] <= MAX_PAIR_RESIDUAL_SHARE * eye_distance(template)

        pairs = None
        found = looked_at(head)
        if landmarks and usable(found):
            given = {n: apply_transform(head.transform, np.asarray(p, np.float64)[None])[0]
                     for n, p in landmarks.items()}
            limit = GIVEN_PART_OFF * eye_distance(template)
            offsets = part_offsets(template, given, skin_points(found), found.scan_points)
            off, doubted = misplaced_parts(offsets, limit)
            if doubted:
                say(f"the face found on {scan_name} disagrees with most parts of the feature points given "
                    f"(more than {limit * 1000:.0f} mm at the template's size); fitting by the points alone")
                found = None
            elif off:
                agree = np.median([v[1] for q, v in offsets.items() if q not in off and q not in UNJUDGED_PARTS])
                for part, (part_names, distance) in sorted(off.items()):
                    say(f"ignored feature points {', '.join(part_names)}: the {PART_WORDS[part]}'s points lie "
                        f"{distance * 1000:.0f} mm from where the face found on {scan_name} has them, the other "
                        f"parts' {agree * 1000:.0f} mm (at the template's size; marked on the wrong feature?)")
                wrong = {n for part_names, _ in off.values() for n in part_names}
                landmarks = {n: p for n, p in landmarks.items() if n not in wrong}
                if len(landmarks) < MIN_GIVEN_POINTS:
                    raise AdaptRefused(f"{landmarks_name}: {len(landmarks)} feature points are left beside the "
                                       f"parts left out; at least {MIN_GIVEN_POINTS} are needed (correct or remove "
                                       "that part's points)")
                head = placed_by(landmarks)
                found = looked_at(head)
        if not landmarks and not usable(found):
            # a face scan leaves up and down open: its face upside down may match the template's
            # (a beard taken for a brow); the face-landmark model tells, on the other poses' renders
            for other in other_poses(template, V, F, head):
                try:
                    found_other = looked_at(other)
                except AdaptRefused:
                    continue
                if usable(found_other):
                    head, found = other, found_other
                    pose_source = "searched, turned over (the face found)"
                    say(f"{scan_name}: no face showed in the head's first pose; found it in another")
                    break
        if not landmarks and usable(found):
            # the face found may say the pose is turned (a face scan's pose from the face alone
            # can be 30-40 degrees off about up, and the face is then fitted turned on its skull)
            # or sized wrong (a face scan's unit then goes unknown, and the head keeps that size):
            # the head is placed again by the face's own points, and looked at again. Where the
            # unit is known the face frame has the person's size, and the face's size over the
            # template's is the person's, not the pose's error (a bust 0.78x the template in
            # metres was placed again and lost its unit: a head 1.3x the person's)
            turn, size_off = pairs_off(found)
            if head.unit != "unknown":
                size_off = 1.0
            if turn > MAX_PAIRS_TURN or size_off > MAX_PAIRS_SCALE:
                placed = head_from_landmarks(template, V, F, skin_points(found),
                                             apply_transform(np.linalg.inv(head.transform), found.scan_points))
                try:
                    found_placed = looked_at(placed) if placed.trusted else None
                except AdaptRefused:  # too little of the scan where the face places it: keep the pose
                    found_placed = None
                if usable(found_placed) and (head.unit == "unknown" or placed.unit != "unknown"):
                    turn_placed, size_placed = pairs_off(found_placed)
                    if placed.unit != "unknown":
                        size_placed = 1.0  # the face frame has the person's size: see above
                    # better where it was off, and no worse than the limit where it was not
                    if (turn_placed < turn if turn > MAX_PAIRS_TURN else turn_placed <= MAX_PAIRS_TURN) and \
                            (size_placed < size_off if size_off > MAX_PAIRS_SCALE else size_placed <= MAX_PAIRS_SCALE):
                        head, found = placed, found_placed
                        pose_source = "the face found"
                        why = [f"turned {turn:.0f} degrees from the head's pose"] if turn > MAX_PAIRS_TURN else []
                        if size_off > MAX_PAIRS_SCALE:
                            why.append(f"{size_off:.2f}x the size the head's pose gives it")
                        say(f"{scan_name}: the face found was {' and '.join(why)}; the head is placed by the face")
        if found is None or len(found.face) < MIN_PAIRS:
            if not landmarks:
                raise AdaptRefused(f"{scan_name}: no face found on the head part of the scan (eyes, nose and "
                                   "mouth); give feature points with --landmarks")
            found = None
        elif found.report["similarity_residual_m"] > MAX_PAIR_RESIDUAL_SHARE * eye_distance(template):
            if not landmarks:
                raise AdaptRefused(
                    f"{scan_name}: the face found on the scan does not match the template's (its points lie "
                    f"{found.report['similarity_residual_m'] * 1000:.1f} mm RMS from a similar placement; at most "
                    f"{MAX_PAIR_RESIDUAL_SHARE * eye_distance(template) * 1000:.1f} mm expected); give feature "
                    "points with --landmarks")
            found = None
        else:
            pairs = (found.face, found.bary, found.scan_points)
        model, report = adapt_to_scan(template, V, F, head, pairs, landmarks)
    except ValueError as exc:
        raise AdaptRefused(f"{scan_name}: {exc}") from exc
    if found is not None:
        report["feature_pair_search"] = found.report
    report["confidence"] = {
        "head_found": head.trusted, "face_coverage_after_pose": head.face_coverage,
        "pose_residual_m": head.residual, "feature_pairs": 0 if found is None else int(len(found.face)),
        "pair_residual_share_of_eye_distance": None if found is None else
        found.report["similarity_residual_m"] / eye_distance(template),
        "landmarks_given": len(landmarks or {}), "head_placed_by": pose_source}
    report["feature_points_on_scan"] = {n: apply_transform(model.scan_transform, p[None])[0].tolist()
                                        for n, p in model.feature_point_positions().items()
                                        if model.feature_points[n].part == "skin"}
    return model, report, head.keep
