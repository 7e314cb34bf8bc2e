"""`fae adapt` on scans as users bring them: whole busts on a plinth, in any pose and unit,
with no feature points. The head must be found and cut from the rest, fitted without a
single fold, measured honestly in the scan's frame, and refused (exit 2) when fae cannot
trust it.

The suite makes its own bust from the shipped head (fae.adapt.synthetic.bust_scan: the head
warped by a smooth random field, 8 % larger, on shoulders and a plinth, turned, in mm) and
also runs the three scanned busts of ../shared/data when they are there.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from fae.adapt.calibration import apply_transform
from fae.adapt.errors import scan_fit_errors
from fae.adapt.geometry import per_face_normals
from fae.adapt.head_pose import find_head, kept_part
from fae.adapt.errors import surface
from fae.adapt.nonrigid import (PROJECT_TURN, blend_away_folds, fit_to_scan, folded_triangles, projected_part_way,
                                scan_pairs)
from fae.adapt.synthetic import template_bust
from fae.anatomy.checks import facemodel_problems
from fae.animate.verify import passed_fraction, verify_faps
from fae.data import shipped_head_path
from fae.linalg import turn_between
from fae.cli import main
from fae.commands.adapt import lids_off_their_eyes
from fae.io.facemodel_gltf import read_facemodel

import importlib.util

needs_mediapipe = pytest.mark.skipif(importlib.util.find_spec("mediapipe") is None,
                                     reason="feature points on a scan need MediaPipe (pip install 'fae[landmarks]')")

BUSTS = ("marble_bust", "man_with_wreath", "demosthenes")


@pytest.fixture(scope="module")
def template():
    return read_facemodel(shipped_head_path())


@pytest.fixture(scope="module")
def bust(template):
    return template_bust(template)


@pytest.fixture(scope="module")
def adapted_bust(bust, tmp_path_factory):
    d = tmp_path_factory.mktemp("bust")
    scan = d / "bust.obj"
    trimesh.Trimesh(bust.vertices, bust.faces, process=False).export(scan)
    out, rep, cmp = d / "head.glb", d / "report.json", d / "compare.png"
    code = main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--compare", str(cmp), "--no-calibrate"])
    return code, out, json.loads(rep.read_text()) if rep.exists() else None, cmp


def test_the_head_is_found_in_a_turned_bust_and_the_plinth_left_out(template, bust):
    head = find_head(template, bust.vertices, bust.faces)
    assert head.trusted
    assert head.unit == "mm"
    # the scan's vertices are the head's, then the chest's and plinth's (in that order)
    n_head = len(bust.truth_vertices)
    kept = np.flatnonzero(head.keep)
    assert kept.max() < n_head + 0.1 * (len(bust.vertices) - n_head)  # at most a rim of the chest
    assert np.mean(kept < n_head) > 0.95
    # most of the head is kept (the neck below the template's own is not)
    assert head.keep[:n_head].mean() > 0.8
    # the pose: the face frame found maps the scan back onto the truth, up to the scale
    truth_in_scan = apply_transform(bust.to_scan, bust.truth_vertices)
    X = apply_transform(head.transform, truth_in_scan)
    assert np.linalg.norm(X.mean(axis=0) - bust.truth_vertices.mean(axis=0)) < 0.02
    R_true = bust.to_scan[:3, :3] / np.cbrt(np.linalg.det(bust.to_scan[:3, :3]))
    R_found = head.template_to_scan[:3, :3] / np.cbrt(np.linalg.det(head.template_to_scan[:3, :3]))
    angle = np.degrees(np.arccos(np.clip((np.trace(R_true.T @ R_found) - 1) / 2, -1, 1)))
    assert angle < 5.0  # turned 180 degrees, the centroid test alone would pass at 2.3 cm


def test_the_head_is_found_on_a_bust_standing_on_a_tall_column(template, bust):
    """A bust on a column three times its height: the head is a ninth of the scan's extent
    along its up, below the smallest share the pose search started from (a third); its
    starts, too large to shrink onto the head, ended upside down (173 degrees off, the face
    pressed to the column, 77 % of it 'covered'; 91 degrees on a column half as tall)."""
    V = np.asarray(bust.vertices, np.float64)
    up = bust.to_scan[:3, 1] / np.linalg.norm(bust.to_scan[:3, 1])  # the face frame's +y in the scan
    along = V @ up
    height = float(np.ptp(along))
    column = trimesh.creation.cylinder(radius=0.25 * height, height=3.0 * height, sections=48)
    cv = np.asarray(column.vertices) @ turn_between(np.array([0.0, 0.0, 1.0]), up).T
    cv += V.mean(axis=0) - up * (np.dot(V.mean(axis=0), up) - along.min() + 1.5 * height)
    scan_V = np.vstack([V, cv])
    scan_F = np.vstack([bust.faces, np.asarray(column.faces) + len(V)])
    head = find_head(template, scan_V, scan_F)
    assert head.trusted
    R_true = bust.to_scan[:3, :3] / np.cbrt(np.linalg.det(bust.to_scan[:3, :3]))
    R_found = head.template_to_scan[:3, :3] / np.cbrt(np.linalg.det(head.template_to_scan[:3, :3]))
    assert np.degrees(np.arccos(np.clip((np.trace(R_true.T @ R_found) - 1) / 2, -1, 1))) < 5.0
    assert not head.keep[len(V):].any()  # nothing of the column


@pytest.mark.parametrize("other", ["a ball 50 m away", "a second bust beside it"])
def test_the_head_is_found_in_a_scan_with_a_far_piece(template, bust, other):
    """A scan whose extent a far piece sets: the pose search sized its starts to the whole
    scan and found no head (a ball 50 m off: face covered 37 %; two busts 15 cm apart:
    55 %). The pieces far apart are searched alone; of two heads, one is fitted and the
    count reported."""
    V = np.asarray(bust.vertices, np.float64)
    size = float(np.linalg.norm(np.ptp(V, axis=0)))
    if other == "a ball 50 m away":
        ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5 * size)
        extra_V, extra_F = np.asarray(ball.vertices) + V.mean(axis=0) + [80.0 * size, 0.0, 0.0], np.asarray(ball.faces)
    else:
        extra_V, extra_F = V + [np.ptp(V[:, 0]) + 0.25 * size, 0.0, 0.0], np.asarray(bust.faces)
    scan_V = np.vstack([V, extra_V])
    scan_F = np.vstack([bust.faces, extra_F + len(V)])
    head = find_head(template, scan_V, scan_F)
    assert head.trusted
    assert head.heads == (2 if other == "a second bust beside it" else 1)
    kept = np.flatnonzero(head.keep)
    if other == "a ball 50 m away":
        assert (kept < len(V)).all()  # nothing of the ball
    else:
        assert (kept < len(V)).all() or (kept >= len(V)).all()  # one head, not a piece of each
    assert head.report(scan_V)["heads_found"] == head.heads


@needs_mediapipe
@pytest.mark.slow
def test_fae_adapt_says_which_of_two_busts_it_fitted(bust, tmp_path, capsys):
    V = np.asarray(bust.vertices, np.float64)
    shift = np.ptp(V[:, 0]) + 0.25 * float(np.linalg.norm(np.ptp(V, axis=0)))
    path, out, rep = tmp_path / "two.ply", tmp_path / "head.glb", tmp_path / "r.json"
    trimesh.Trimesh(np.vstack([V, V + [shift, 0.0, 0.0]]), np.vstack([bust.faces, np.asarray(bust.faces) + len(V)]),
                    process=False).export(path)
    assert main(["adapt", str(path), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    assert "2 heads found in the scan" in capsys.readouterr().err
    report = json.loads(rep.read_text())
    assert report["head_part"]["heads_found"] == 2
    assert report["errors"]["face_to_scan_rms_rel"] < 0.001


@needs_mediapipe
@pytest.mark.slow
def test_a_bust_becomes_a_whole_head_on_its_scan(adapted_bust, bust, template):
    code, out, report, cmp = adapted_bust
    assert code == 0, report and report.get("verdict")
    model = read_facemodel(out)
    assert facemodel_problems(model) == []
    assert report["folded_triangles"]["all"] == 0
    e = report["errors"]
    assert e["face_to_scan_rms_rel"] < 0.001 and e["face_coverage"] > 0.95
    # the neck stiffens towards its end, so its base no longer follows the shoulders' flare
    # (0.18 %; 0.12 % when it did); the head without the neck 0.07 %
    assert e["scan_to_skin_rms_rel"] < 0.002 and e["scan_coverage"] > 0.9
    assert e["head_to_skin_rms_rel"] < 0.001
    # against the truth, not the fitted scan: the face's skin in the truth's frame
    from fae.adapt.errors import FACE_REGIONS
    from fae.adapt.from_scan import in_regions
    from fae.adapt.transfer import visible_skin

    S = np.linalg.inv(bust.to_scan) @ model.scan_transform
    face = in_regions(template, FACE_REGIONS) & visible_skin(template)
    skin = apply_transform(S, model.skin_vertices[face])
    d = trimesh.proximity.closest_point(trimesh.Trimesh(bust.truth_vertices, bust.truth_faces, process=False),
                                        skin)[1]
    assert np.sqrt(np.mean(d ** 2)) < 0.5e-3
    # the head keeps the person's size: the bust is 8 % larger than the template
    size = np.ptp(model.skin_vertices[:, 0]) / np.ptp(template.skin_vertices[:, 0])
    assert 1.03 < size < 1.13
    assert report["head_part"]["head_vertices"] < report["head_part"]["scan_vertices"]
    # the lids keep to their eyeballs as the template's do (0.8 mm): no deep-set eyes told of
    gaps = report["lid_gap_m"]
    assert set(gaps) == {"eye_l", "eye_r"}
    assert all(0.0 < g[lid] < 0.002 for g in gaps.values() for lid in ("upper", "lower")), gaps
    assert lids_off_their_eyes(report) is None
    from PIL import Image

    assert Image.open(cmp).size == (3 * 360, 2 * 360)


@needs_mediapipe
@pytest.mark.slow
def test_a_bust_looking_aside_45_degrees_becomes_a_head(template, tmp_path):
    """A bust sculpted with its head turned 45 degrees on its neck (the suite's own bust,
    fae.adapt.synthetic.turned_on_its_neck): the head is found and fitted as a head, not
    as one turned on the shoulders' axes (measured: face 0.016 % of the diagonal, the head
    without the neck 0.08 %, nothing folded; -45 degrees 0.040 / 0.105 %)."""
    from fae.adapt.synthetic import turned_on_its_neck

    bust = template_bust(template, V=turned_on_its_neck(template, 45.0))
    scan = tmp_path / "aside.obj"
    trimesh.Trimesh(bust.vertices, bust.faces, process=False).export(scan)
    out, rep = tmp_path / "head.glb", tmp_path / "report.json"
    code = main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--no-calibrate"])
    report = json.loads(rep.read_text())
    assert code == 0, report.get("verdict")
    assert facemodel_problems(read_facemodel(out)) == []
    assert report["folded_triangles"]["all"] == 0
    e = report["errors"]
    assert e["face_to_scan_rms_rel"] < 0.001 and e["face_coverage"] > 0.95
    assert e["head_to_skin_rms_rel"] < 0.002


@needs_mediapipe
@pytest.mark.slow
def test_lips_reach_a_scan_whose_mouth_is_a_slit(template, tmp_path):
    """A scanner sees no lips' inner side: a mask's or a face scan's mouth is a slit, a hole
    whose edge is the lips' rim. The suite's bust with fuller lips (2.5 mm forward round
    the mouth) and only the lips' seen side: the skin within 8 mm of the slit paired with
    nothing (the scan's rim rule), and the lips stayed where the template had them (the
    face 0.025 % of the diagonal off its scan, the lower lip 0.87 mm RMS off the truth; on
    the menpo3d mask, 2-4 mm at the mouth corners). A hole's edge now keeps only the skin
    within 2 mm of it from the scan."""
    from fae.adapt.from_scan import in_regions
    from fae.adapt.synthetic import bust_scan
    from fae.adapt.transfer import visible_skin

    V = np.array(template.skin_vertices)
    F = np.asarray(template.skin_faces)
    fp = template.feature_point_positions()
    mouth = 0.5 * (fp["8.1"] + fp["8.2"])
    V[:, 2] += 0.0025 * np.exp(-np.sum(((V - mouth) / np.array([0.02, 0.01, 0.02])) ** 2, axis=1))
    seen = visible_skin(template)
    lining = np.asarray(template.skin_region)[F[:, 0]] == template.region_names.index("mouth_cavity")
    inner_lips = in_regions(template, ["lip_upper", "lip_lower"])[F].all(axis=1) & ~seen[F].all(axis=1)
    skin_points = {n: p for n, p in fp.items() if template.feature_points[n].part == "skin"}
    bust = bust_scan(V, F, skin_points, seed=3, drop_faces=lining | inner_lips)
    scan, out, rep = tmp_path / "slit.obj", tmp_path / "head.glb", tmp_path / "report.json"
    trimesh.Trimesh(bust.vertices, bust.faces, process=False).export(scan)
    assert main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    report = json.loads(rep.read_text())
    assert report["folded_triangles"]["all"] == 0
    assert report["errors"]["face_to_scan_rms_rel"] < 1e-4
    model = read_facemodel(out)
    S = np.linalg.inv(bust.to_scan) @ model.scan_transform
    lower = in_regions(template, ["lip_lower"]) & seen
    d = trimesh.proximity.closest_point(trimesh.Trimesh(bust.truth_vertices, bust.truth_faces, process=False),
                                        apply_transform(S, model.skin_vertices[lower]))[1]
    assert np.sqrt(np.mean(d ** 2)) < 0.6e-3


@needs_mediapipe
@pytest.mark.slow
def test_a_scan_without_a_face_is_refused(tmp_path, capsys):
    scan = tmp_path / "pot.obj"
    pot = trimesh.creation.capsule(height=0.2, radius=0.08, count=[32, 32])
    pot.export(scan)
    out = tmp_path / "head.glb"
    assert main(["adapt", str(scan), "-o", str(out), "--no-calibrate"]) == 2
    err = capsys.readouterr().err
    assert "--landmarks" in err
    assert not out.exists()


@needs_mediapipe
@pytest.mark.slow
def test_given_feature_points_with_wrong_ones_still_give_a_whole_head(bust, template, tmp_path, capsys):
    rng = np.random.default_rng(5)
    names = sorted(bust.landmarks)
    some = [names[i] for i in rng.choice(len(names), 14, replace=False)]
    pts = {n: np.asarray(bust.landmarks[n], float) for n in some}
    for n in some[:3]:  # three placed 4 cm off
        pts[n] = pts[n] + np.array([40.0, -25.0, 10.0])
    scan, lm = tmp_path / "bust.obj", tmp_path / "lm.json"
    trimesh.Trimesh(bust.vertices, bust.faces, process=False).export(scan)
    lm.write_text(json.dumps({n: p.tolist() for n, p in pts.items()}))
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(scan), "--landmarks", str(lm), "-o", str(out), "--report", str(rep),
                 "--no-calibrate"]) == 0
    assert "disagrees with the others" in capsys.readouterr().err
    report = json.loads(rep.read_text())
    assert report["folded_triangles"]["all"] == 0
    assert report["errors"]["face_to_scan_rms_rel"] < 0.001


def test_a_part_of_the_feature_points_off_the_found_face_is_told_from_a_doubtful_face(template):
    """part_offsets / misplaced_parts without a face-landmark model: pairs laid on the
    template's own skin (1 mm of noise) agree with the template's points; the mouth's
    moved 30 mm is the one part left out; most parts moved put the found face in doubt."""
    from fae.adapt.workflow import GIVEN_PART_OFF, eye_distance, misplaced_parts, part_offsets
    from fae.anatomy.surface_points import markup_positions
    from fae.mpeg4.fdps import face_part

    fdp = markup_positions(template)
    names = [n for n in fdp if template.feature_points[n].part == "skin" and face_part(n) is not None]
    skin = np.asarray(template.skin_vertices)[::3]
    found = skin + np.random.default_rng(0).normal(scale=0.001, size=skin.shape)
    limit = GIVEN_PART_OFF * eye_distance(template)
    offsets = part_offsets(template, {n: fdp[n] for n in names}, skin, found)
    assert {"mouth", "nose", "eye_l", "eye_r", "brow_l", "brow_r"} <= set(offsets)
    assert max(d for _, d in offsets.values()) < 0.004
    assert misplaced_parts(offsets, limit) == ({}, False)
    down = np.array([0.0, -0.03, 0.0])
    moved = {n: fdp[n] + (down if face_part(n) == "mouth" else 0.0) for n in names}
    off, doubted = misplaced_parts(part_offsets(template, moved, skin, found), limit)
    assert not doubted and set(off) == {"mouth"}
    assert set(off["mouth"][0]) == {n for n in names if face_part(n) == "mouth"} and off["mouth"][1] > 0.025
    most = {n: fdp[n] + (down if face_part(n) != "nose" else 0.0) for n in names}
    assert misplaced_parts(part_offsets(template, most, skin, found), limit) == ({}, True)


def test_a_scans_rim_is_its_outline_not_its_slits_or_jagged_openings():
    """near_rim on a face-like sheet (0.3 m across) with a mouth's slit and an eye opening
    cut along a sawtooth (as long as half the outline), and on a closed head whose only
    opening is a mouth's slit: only the outline is rim."""
    from fae.adapt.nonrigid import EDGE_REACH, near_rim

    n = 121
    x, y = np.meshgrid(np.linspace(-0.15, 0.15, n), np.linspace(-0.15, 0.15, n))
    V = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    F = np.vstack([np.column_stack([a, a + 1, a + n]), np.column_stack([a + 1, a + n + 1, a + n])])
    c = V[F].mean(axis=1)
    slit = (np.abs(c[:, 0]) < 0.03) & (np.abs(c[:, 1] + 0.07) < 0.002)
    eye = (np.abs(c[:, 0] - 0.06) < 0.03) & (np.abs(c[:, 1] - 0.05) < 0.01 + 0.006 * np.sign(np.sin(c[:, 0] * 900)))
    sheet = surface(V, F[~slit & ~eye])
    rim = near_rim(sheet)
    fc = sheet.V[sheet.F].mean(axis=1)
    inset = 0.15 - np.max(np.abs(fc[:, :2]), axis=1)  # from the outline, metres
    assert rim[inset < 0.5 * EDGE_REACH].all()
    assert not rim[inset > 1.5 * EDGE_REACH].any()  # where the slit and the eye opening are
    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.1)
    bc = ball.triangles_center
    closed = surface(ball.vertices, ball.faces[~((np.abs(bc[:, 0]) < 0.025) & (np.abs(bc[:, 1] + 0.05) < 0.004)
                                                  & (bc[:, 2] > 0))])
    assert closed.boundary.any() and not near_rim(closed).any()


@needs_mediapipe
@pytest.mark.slow
def test_a_mouth_marked_on_the_chin_is_left_out_and_the_scans_mouth_kept(bust, template, tmp_path, capsys):
    """A marker can place a whole part on the wrong feature: the mouth's 18 points moved 0.9
    of the way from the lower lip to the chin, along the surface. Each agrees with its own
    part and the scan holds them all, so neither check of single points caught them, and
    the fit laid the template's mouth on the chin, trusted. The face found on the scan
    has its mouth elsewhere: those points are left out, with a notice naming the part, and
    the head's lips are the scan's."""
    from fae.mpeg4.fdps import face_part

    names = [n for n in bust.landmarks if face_part(n) is not None]
    pts = {n: np.asarray(bust.landmarks[n], float) for n in names}
    mouth = [n for n in names if face_part(n) == "mouth"]
    assert len(mouth) >= 10
    shift = 0.9 * (pts["2.1"] - pts["8.2"])
    surface = trimesh.Trimesh(bust.vertices, bust.faces, process=False)
    moved = trimesh.proximity.closest_point(surface, np.array([pts[n] + shift for n in mouth]))[0]
    given = dict(pts)
    given.update({n: p for n, p in zip(mouth, moved)})
    scan, lm = tmp_path / "bust.obj", tmp_path / "lm.json"
    surface.export(scan)
    lm.write_text(json.dumps({n: p.tolist() for n, p in given.items()}))
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(scan), "--landmarks", str(lm), "-o", str(out), "--report", str(rep),
                 "--no-calibrate"]) == 0
    err = capsys.readouterr().err
    assert "the mouth's points lie" in err and "8.2" in err
    report = json.loads(rep.read_text())
    assert not set(mouth) & set(report["landmarks_used"])
    assert report["folded_triangles"]["all"] == 0
    on_scan = report["feature_points_on_scan"]
    # mm, the scan's unit: 2.4-5.1 (the lower lip's the most; 0.7 mm more since the template's
    # upper lip lost its caps); the chin lies 20 mm and more away
    for n in ("8.1", "8.2", "8.3", "8.4"):
        assert np.linalg.norm(np.asarray(on_scan[n]) - pts[n]) < 6.0, n


@needs_mediapipe
@pytest.mark.slow
def test_a_scan_wound_inside_out_is_turned_outward(bust, tmp_path, capsys):
    """Exporters and mirroring leave scans wound inside out: the fit, pairing by normals,
    found no face on the turned marble bust and refused it, blaming the feature points."""
    scan = tmp_path / "inside_out.obj"
    trimesh.Trimesh(bust.vertices, bust.faces[:, ::-1], process=False).export(scan)
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    assert "its faces are wound inside out" in capsys.readouterr().err
    report = json.loads(rep.read_text())
    assert report["scan_turned_outward"] and report["errors"]["face_to_scan_rms_rel"] < 0.001


def test_output_over_the_scan_is_refused(tmp_path, capsys):
    scan = tmp_path / "s.obj"
    trimesh.creation.icosphere().export(scan)
    before = scan.read_bytes()
    assert main(["adapt", str(scan), "-o", str(scan)]) == 2
    assert "overwrite" in capsys.readouterr().err
    assert scan.read_bytes() == before


def test_folds_are_counted_on_real_triangles_only(template):
    P, F = template.skin_vertices, np.asarray(template.skin_faces, np.int64)
    assert not folded_triangles(P, P, F).any()  # the template's collapsed seam triangles do not count
    X = P.copy()
    nose = int(np.argmax(P[:, 2]))
    ring = np.unique(F[(F == nose).any(axis=1)])
    X[nose] -= 3 * (P[ring].mean(axis=0) - P[nose]) + np.array([0.0, 0.0, 0.02])  # push the tip through
    bad = folded_triangles(P, X, F)
    assert bad.any() and np.all(np.isin(F[bad], ring).all(axis=1))
    Y, moved = blend_away_folds(P, P, X, F)
    assert not folded_triangles(P, Y, F).any() and moved > 0
    far = np.linalg.norm(P - P[nose], axis=1) > 0.03
    assert moved < 300 and np.allclose(Y[far], X[far])  # the blend stays around the fold


def test_a_vertex_whose_way_onto_the_scan_would_turn_a_triangle_goes_part_of_it():
    # a hexagonal fan 1 cm across: its centre raised 2 cm onto a scan point would tilt every
    # triangle 67 degrees; half the way tilts them 49. The step used to be all or nothing
    # (the centre stayed put, 2 cm off the scan); the ring lies on the scan already
    angles = np.arange(6) * np.pi / 3
    X = np.vstack([[0.0, 0.0, 0.0], np.stack([np.cos(angles), np.sin(angles), np.zeros(6)], axis=1) * 0.01])
    F = np.array([[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)])
    idx = np.arange(7)
    Q = X.copy()
    Q[0, 2] = 0.02
    Y = projected_part_way(X, F, idx, Q, X)
    assert np.allclose(Y[0], [0.0, 0.0, 0.01]) and np.allclose(Y[1:], X[1:])
    assert not folded_triangles(X, Y, F, PROJECT_TURN).any()
    held = np.zeros(7, dtype=bool)
    held[0] = True  # a lip's vertex goes all the way or not at all
    assert np.allclose(projected_part_way(X, F, idx, Q, X, all_or_nothing=held), X)
    Q[0, 2] = 0.005  # 30 degrees: all the way
    assert np.allclose(projected_part_way(X, F, idx, Q, X), Q)
    # two triangles folded against the template before the step (a ring vertex pulled across
    # the centre) are no move's fault: the centre still goes its 0.5 mm
    X2 = X.copy()
    X2[1] = [-0.003, 0.0, 0.0]
    assert folded_triangles(X, X2, F).sum() == 2
    Q2 = X2.copy()
    Q2[0, 2] = 0.0005
    assert np.allclose(projected_part_way(X2, F, idx, Q2, X), Q2)


def test_skin_over_a_hollow_pairs_with_its_floor_not_its_steep_side():
    # a scan with a trough 8 mm deep and 6 mm wide (a sculpted inner eye corner): skin
    # bridging it has its closest scan points on the trough's steep side, whose normals
    # face sideways; along its own normal it finds the floor
    xz = [(-0.06, 0.0), (-0.04, 0.0), (-0.02, 0.0), (-0.0031, 0.0), (-0.00305, -0.004), (-0.003, -0.008),
          (0.003, -0.008), (0.00305, -0.004), (0.0031, 0.0), (0.02, 0.0), (0.04, 0.0), (0.06, 0.0)]
    ys = np.linspace(-0.03, 0.03, 13)
    V = np.array([[x, y, z] for y in ys for x, z in xz])
    m = len(xz)
    F = [[j * m + i, j * m + i + 1, (j + 1) * m + i + 1] for j in range(len(ys) - 1) for i in range(m - 1)]
    F += [[j * m + i, (j + 1) * m + i + 1, (j + 1) * m + i] for j in range(len(ys) - 1) for i in range(m - 1)]
    scan = surface(V, np.array(F))
    X = np.array([[-0.001, 0.0, -0.004], [0.02, 0.0, 0.0005]])  # 2 mm from the side, 4 mm over the floor; the flat
    N = np.tile([0.0, 0.0, 1.0], (2, 1))
    idx, Q = scan_pairs(X, N, scan, 0.02, np.ones(2, bool))
    assert list(idx) == [0, 1]
    assert np.allclose(Q[0], [-0.001, 0.0, -0.008], atol=1e-6) and np.allclose(Q[1], [0.02, 0.0, 0.0], atol=1e-6)
    # the floor farther than RAY_SHARE x the side: no pair at all
    idx, _ = scan_pairs(np.array([[-0.0027, 0.0, -0.004]]), N[:1], scan, 0.02, np.ones(1, bool))
    assert len(idx) == 0


def test_skin_whose_shape_lacks_a_rim_of_its_scan_is_pulled_onto_it():
    # an ear's dish against a scanned ear whose rolled rim stands beyond it: the skin's own
    # closest points all lie on the flat, and only the scan's points on the rim can pull it there
    def grid(xs, ys):
        V = np.array([[x, y, 0.0] for y in ys for x in xs])
        m = len(xs)
        F = [[j * m + i, j * m + i + 1, (j + 1) * m + i + 1] for j in range(len(ys) - 1) for i in range(m - 1)]
        F += [[j * m + i, (j + 1) * m + i + 1, (j + 1) * m + i] for j in range(len(ys) - 1) for i in range(m - 1)]
        return V, np.array(F)

    P, F = grid(np.linspace(-0.03, 0.03, 13), np.linspace(-0.03, 0.03, 13))
    S, SF = grid(np.linspace(-0.045, 0.045, 61), np.linspace(-0.045, 0.045, 61))
    S[:, 2] += 0.004 * np.exp(-((S[:, 0] - 0.036) / 0.004) ** 2)  # a rim 4 mm high, 6 mm beyond the skin's edge
    scan = surface(S, SF)
    rim = (np.abs(S[:, 0]) < 0.038) & (np.abs(S[:, 1]) < 0.025)
    reach, rms = [], []
    for fill in (None, np.ones(len(P), bool)):
        fit = fit_to_scan(P, F, scan, np.ones(len(P), bool), fill=fill)
        assert fit.folded == 0
        d = surface(fit.vertices, F).query.closest_points(S[rim], 0.02)[1]
        reach.append(fit.vertices[:, 0].max())
        rms.append(np.sqrt(np.mean(d ** 2)))
    assert reach[0] < 0.031 and rms[0] > 0.002  # without the scan's pull: the skin ends at its own edge
    assert reach[1] > 0.034 and rms[1] < 0.0008  # with it: onto the rim (2.4 -> 0.5 mm)


def test_errors_are_measured_in_the_scan_frame_with_coverage():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=100.0)  # a scan in mm
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    skin = V * 1.01  # 1 mm outside
    face = V[:, 2] > 50
    e = scan_fit_errors(skin, F, face, V, F)
    assert abs(e["face_to_scan_rms"] - 1.0) < 0.05 and e["face_coverage"] == 1.0
    # half the scan missing: its coverage says so, the RMS does not grow
    half = V[:, 0] > 0
    Vh, Fh = kept_part(V, F, half)
    e2 = scan_fit_errors(skin, F, face, Vh, Fh)
    assert e2["face_coverage"] < 0.7 and abs(e2["face_to_scan_rms"] - 1.0) < 0.1
    # the head without the neck: a "neck" (the bottom cap) 5 mm off is left out of that figure
    neck = V[:, 1] < -80
    skin2 = skin.copy()
    skin2[neck] = V[neck] * 1.05
    e3 = scan_fit_errors(skin2, F, face, V, F, neck=neck)
    assert e3["scan_to_skin_rms"] > 1.5 and abs(e3["head_to_skin_rms"] - 1.0) < 0.1
    assert 0.8 < e3["head_coverage"] <= 1.0
    # scan the skin does not reach (the neck 3 cm off, past the 2 % of the diagonal a hole
    # may be) drops out of the covered RMS, not out of the one over every point
    skin4 = skin.copy()
    skin4[neck] = V[neck] * 1.3
    e4 = scan_fit_errors(skin4, F, face, V, F)
    assert e4["scan_coverage"] < 0.95 and e4["scan_to_skin_rms"] < 1.5  # 1.3 mm
    assert 5.0 < e4["scan_to_skin_all_rms"] < 10.0  # 7.0 mm
    assert abs(e["scan_to_skin_all_rms"] - e["scan_to_skin_rms"]) < 1e-9  # all covered: the same


def test_per_face_normals_of_the_template_are_unit(template):
    N = per_face_normals(template.skin_vertices, np.asarray(template.skin_faces, np.int64))
    ok = np.linalg.norm(N, axis=1) > 0.5
    assert np.allclose(np.linalg.norm(N[ok], axis=1), 1.0)


def pupil_offsets(model) -> list[float]:
    """Per eye, how far its pupil (3.5, 3.6) lies above or below the middle of its opening
    (fae.adapt.transfer.opening_middle), in shares of the opening's height (3.1-3.3, 3.2-3.4)."""
    from fae.adapt.transfer import opening_middle

    fp = model.feature_point_positions()
    return [abs(fp[pupil][1] - opening_middle(fp, eye)[1]) / (fp[upper][1] - fp[lower][1])
            for eye, pupil, upper, lower in (("eye_l", "3.5", "3.1", "3.3"), ("eye_r", "3.6", "3.2", "3.4"))]


def neck_creases(model, more_than: float = 30.0) -> int:
    """Edges between two neck triangles of `model`'s skin bent `more_than` degrees further
    than the template's (the shipped head shares the adapted head's neck triangles; a fitted
    head's own differ only in the upper lids, fae.adapt.transfer.fitted_caps_flipped)."""
    from fae.adapt.untangle import dihedral_turns
    from fae.data import shipped_head_path
    from fae.mesh import triangle_pairs

    template = read_facemodel(shipped_head_path())
    F = np.asarray(model.skin_faces)
    neck = (np.asarray(model.skin_region)[F] == model.region_names.index("neck")).all(axis=1)
    pairs = triangle_pairs(F)
    pairs = pairs[neck[pairs].all(axis=1)]
    turn = dihedral_turns(model.skin_vertices, F, pairs) - dihedral_turns(template.skin_vertices, F, pairs)
    return int(np.sum(turn > np.radians(more_than)))


@needs_mediapipe
@pytest.mark.slow
@pytest.mark.parametrize("name", BUSTS)
def test_a_scanned_bust_becomes_a_head(shared_data, name, tmp_path, capsys):
    scan = shared_data / "heads" / "busts" / name / f"{name}.obj"
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    report = json.loads(rep.read_text())
    # the sculpted upper lids lie 5.2-10.5 mm off the eyeballs placed in their sockets (the
    # lower 1.6-4.6 mm, the template's 0.8): told on stderr, as the report has it
    told = lids_off_their_eyes(report)
    assert set(report["lid_gap_m"]) == {"eye_l", "eye_r"}
    assert min(g["upper"] for g in report["lid_gap_m"].values()) > 0.003, report["lid_gap_m"]
    assert told is not None and told in capsys.readouterr().err
    assert report["folded_triangles"]["all"] == 0
    e = report["errors"]
    assert e["face_to_scan_rms_rel"] < 0.001 and e["face_coverage"] > 0.95  # 0.058-0.096 %
    # the scan's points pull the ears, scalp and neck too: scan -> skin 0.20 / 0.33 / 0.28 %
    # (the neck beside the cut where it runs into the drapery pulls nothing: 0.19 / 0.28 /
    # 0.24 % when it did), without the neck 0.17 / 0.28 / 0.20 % (0.29 / 0.32 / 0.28 % and
    # 0.28 / 0.33 / 0.23 % before the ears, scalp and neck were pulled)
    most, most_head, creases = {"marble_bust": (0.0024, 0.0019, 210), "man_with_wreath": (0.0036, 0.0030, 240),
                                "demosthenes": (0.0031, 0.0022, 300)}[name]
    assert e["scan_to_skin_rms_rel"] < most and e["head_to_skin_rms_rel"] < most_head
    # the neck keeps a neck's smooth shape where the bust's runs into its base: edges bent
    # 30 degrees more than the template's there 178 / 191 / 238 (270 / 201 / 381 with a
    # ledge along the cut; the wreath's neck had none, so its bound only guards)
    assert neck_creases(read_facemodel(out)) < creases
    part = report["head_part"]
    assert part["head_vertices"] < 0.9 * part["scan_vertices"]  # the plinth and shoulders are left out
    assert report["scan_covers_part_of_head"] is False  # the neck's cut alone does not make it a face scan
    assert facemodel_problems(read_facemodel(out)) == []
    # the fit leaves caps in the sculpted upper lids (a corner over 130 degrees: 33 / 30 / 52,
    # the template 2), which crease as the lids close: about half are flipped away (24 / 32 /
    # 56 faces change; 20 / 14 / 23 caps remain)
    from fae.adapt.transfer import FIT_CAP_FLIPPED_REGIONS
    from fae.anatomy.geometry import _corner_angles

    head = read_facemodel(out)
    names, F = list(head.region_names), np.asarray(head.skin_faces, np.int64)
    lids = np.isin(np.asarray(head.skin_region), [names.index(r) for r in FIT_CAP_FLIPPED_REGIONS])[F].sum(axis=1) >= 2
    caps = int(np.sum(lids & (np.degrees(_corner_angles(head.skin_vertices, F).max(axis=1)) > 130.0)))
    assert report["lid_faces_reflipped"] >= 15 and caps <= 26, (report["lid_faces_reflipped"], caps)
    # sculpted eyes leave shallow sockets: the orbit deepens, the eyeballs keep their size (0.6 once)
    assert min(report["eye_scale"].values()) > 0.75, report["eye_scale"]
    # each eye looks out of its opening's middle: its pupil within 12 % of the opening's
    # height of the middle up and down (marble 3 / 0 %, wreath 3 / 10 %, Demosthenes 1 /
    # 4 %; 13-17 / 2-6 / 16-19 % with the template's rest gaze, irises half under the lids)
    assert max(pupil_offsets(read_facemodel(out))) < 0.12
    # the upper incisors' edge sits below the upper lip's inner point, as the template's does
    # (2.7 mm): parted lips show the teeth. Carried with the skin around the mouth alone,
    # the marble bust's stood 2.6 mm above it and its smile showed only the mouth's dark
    fp = read_facemodel(out).feature_point_positions()
    assert fp["2.2"][1] - fp["9.10"][1] > 0.0015
    if name == "marble_bust":
        # calibrated as `fae adapt` does (from the template's mapping), the lower lip corners'
        # raises, probed on part of the skin where the lips press on each other, are checked
        # on the whole skin: they land 1.06 / 1.02x their value (1.80 / 1.58x when the part
        # probes raised their scales from 5.6 to 8.6 / 7.2)
        from fae.animate.calibrate import calibrate
        from fae.animate.player import Player, PlayableHead

        head = calibrate(read_facemodel(out), start=read_facemodel(shipped_head_path()).fap_mapping)
        corners = verify_faps(Player(PlayableHead(head)), faps=[10, 11])
        assert all(r["ratio"] < 1.15 for r in corners), [(r["fap"], round(r["ratio"], 2)) for r in corners]


@needs_mediapipe
@pytest.mark.slow
def test_a_few_feature_points_given_place_the_head_no_worse_than_none(shared_data, tmp_path):
    """The marble bust's midline points alone (placed where `fae adapt` finds them) placed
    its head 25 degrees turned and 1.36x its size from the search's placement, and the head
    came out further from the scan than with no points at all (scan -> skin without the
    neck 0.27 % of the diagonal for 0.16 %, the face 0.060 % for 0.044 %). The search's
    placement is kept where it places the same head; the points still pull the fit."""
    scan = shared_data / "heads" / "busts" / "marble_bust" / "marble_bust.obj"
    if not scan.is_file():
        pytest.skip("marble bust not in the shared data")
    reports = []
    for landmarks in (None, ("9.3", "2.1", "8.1", "2.2", "9.15", "2.3", "8.2")):
        args = ["adapt", str(scan), "-o", str(tmp_path / "head.glb"), "--report", str(tmp_path / "r.json"),
                "--no-calibrate"]
        if landmarks:
            found = reports[0]["feature_points_on_scan"]
            (tmp_path / "midline.json").write_text(json.dumps({n: found[n] for n in landmarks}))
            args += ["--landmarks", str(tmp_path / "midline.json")]
        assert main(args) == 0
        reports.append(json.loads((tmp_path / "r.json").read_text()))
    none, midline = (r["errors"] for r in reports)
    assert reports[1]["confidence"]["head_placed_by"].startswith("searched")
    assert midline["head_to_skin_rms_rel"] < 1.1 * none["head_to_skin_rms_rel"]
    assert midline["face_to_scan_rms_rel"] < 1.1 * none["face_to_scan_rms_rel"]


@needs_mediapipe
@pytest.mark.slow
def test_a_few_feature_points_that_place_a_face_scan_keep_it(shared_data, tmp_path):
    """The menpo3d mask, a face alone, with ten of its own points: their placement lies on
    it, and it stays (the search over a face alone tipped it 38 degrees: the face 0.128 % of
    the diagonal from the scan for 0.059 %)."""
    from fae.io.scan import read_landmarks

    face = shared_data / "heads" / "menpo3d_template"
    if not face.is_dir():
        pytest.skip("menpo3d template not in the shared data")
    points = read_landmarks(face / "template.ljson")
    ten = {n: points[n].tolist() for n in ("9.3", "2.1", "3.7", "3.11", "3.8", "3.12", "8.3", "8.4", "4.1", "4.2")
           if n in points}
    assert len(ten) >= 8
    (tmp_path / "ten.json").write_text(json.dumps(ten))
    assert main(["adapt", str(face / "template.ply"), "--landmarks", str(tmp_path / "ten.json"), "-o",
                 str(tmp_path / "head.glb"), "--report", str(tmp_path / "r.json"), "--no-calibrate"]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["confidence"]["head_placed_by"] == "feature points given"
    assert report["errors"]["face_to_scan_rms_rel"] < 0.001


@needs_mediapipe
@pytest.mark.slow
def test_a_bearded_face_cut_to_a_mask_is_not_fitted_upside_down(shared_data, tmp_path, capsys):
    """Demosthenes' face cut out with its brow and the top of its beard: the head search
    matched the template's face to it upside down (the beard as a brow, 70 % of the face
    covered: trusted) and the face-landmark model found no face on that pose's render, so
    the scan was refused. The pose found by the face alone, or the first one turned over,
    is tried when no face shows; the head comes out right way up."""
    mesh = trimesh.load(shared_data / "heads" / "busts" / "demosthenes" / "demosthenes.obj", force="mesh",
                        process=False)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    # the bust's face frame, as `fae adapt` finds it on the whole bust: origin, scale, +y, +z
    origin, scale = np.array([0.1872, 1.5321, 0.2762]), 6.583
    up, forward = np.array([0.0214, 0.96, 0.279]), np.array([0.0026, -0.2791, 0.9602])
    c = (V[F].mean(axis=1) - origin) / scale
    keep = (c @ forward > 0.0215) & (c @ up > -0.1385) & (c @ up < 0.0998)
    path, out, rep = tmp_path / "mask.obj", tmp_path / "head.glb", tmp_path / "r.json"
    trimesh.Trimesh(V, F[keep], process=False).export(path)
    assert main(["adapt", str(path), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    assert "found it in another" in capsys.readouterr().err
    report = json.loads(rep.read_text())
    assert report["scan_covers_part_of_head"] is True
    assert report["errors"]["face_to_scan_rms_rel"] < 0.0025  # 0.17 %
    model = read_facemodel(out)
    head_up = model.scan_transform[:3, 1] / np.linalg.norm(model.scan_transform[:3, 1])
    assert np.degrees(np.arccos(np.clip(head_up @ up, -1.0, 1.0))) < 25.0
    assert facemodel_problems(model) == []


@needs_mediapipe
@pytest.mark.slow
@pytest.mark.parametrize("holes, radius, behind", [(150, 0.006, 0.0), (100, 0.005, 0.03)])
def test_a_bust_with_many_holes_behind_its_head_becomes_a_whole_head(shared_data, tmp_path, holes, radius, behind):
    """The marble bust with a hundred or more small holes over the back of its head. 150 of
    6 mm: pose starts that fell into a hole shrank to nothing, scored NaN, and crowded the
    best out of the ones refined (face covered 8 %, refused). 100 of 5 mm: the fit's start
    paired the template with the holes' rims and the head came out with the mandible
    through the skin (refused as not whole); pairs by a hole are now left out of it. The
    holes are not the scan's rim: the scan is not taken for part of a head."""
    from scipy.spatial import cKDTree

    mesh = trimesh.load(shared_data / "heads" / "busts" / "marble_bust" / "marble_bust.obj", force="mesh",
                        process=False)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(1)
    behind_head = np.flatnonzero((V[:, 2] < behind) & (V[:, 1] > 0.25))
    gone = cKDTree(V[rng.choice(behind_head, holes, replace=False)]).query(V)[0] < radius
    path, out, rep = tmp_path / "holes.ply", tmp_path / "head.glb", tmp_path / "r.json"
    holed = trimesh.Trimesh(V, F[~gone[F].any(axis=1)], process=False)
    holed.remove_unreferenced_vertices()
    holed.export(path)
    assert main(["adapt", str(path), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    report = json.loads(rep.read_text())
    assert report["scan_covers_part_of_head"] is False
    assert report["errors"]["face_to_scan_rms_rel"] < 0.001
    assert facemodel_problems(read_facemodel(out)) == []


@needs_mediapipe
@pytest.mark.slow
@pytest.mark.parametrize("max_turn", [None, 5.0])
def test_a_face_cut_out_is_not_fitted_turned_on_its_skull(shared_data, tmp_path, capsys, monkeypatch, max_turn):
    """The wreath bust's face cut out: its pose, found by the face alone, was turned 32-37
    degrees about up; the face-landmark model still found the face on that render, and the
    face was fitted turned on the skull (one ear, the neck twisted), trusted. A face found
    turned more than MAX_PAIRS_TURN from the pose places the head again. With the current
    template the face is found turned 13 degrees and the first pose kept (the head's axes
    8 degrees from the whole bust's); a lower limit (5) makes the face place the head
    (5-7 degrees from them). Either lands within 15 degrees."""
    import fae.adapt.workflow

    if max_turn is not None:
        monkeypatch.setattr(fae.adapt.workflow, "MAX_PAIRS_TURN", max_turn)
    mesh = trimesh.load(shared_data / "heads" / "busts" / "man_with_wreath" / "man_with_wreath.obj", force="mesh",
                        process=False)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    inside = (V[:, 2] > 0.10) & (V[:, 1] > 0.22)
    path, out = tmp_path / "face.obj", tmp_path / "head.glb"
    face = trimesh.Trimesh(V, F[inside[F].all(axis=1)], process=False)
    face.remove_unreferenced_vertices()
    face.export(path)
    assert main(["adapt", str(path), "-o", str(out), "--no-calibrate"]) == 0
    assert ("the head is placed by the face" in capsys.readouterr().err) == (max_turn is not None)
    model = read_facemodel(out)
    # the whole bust's face frame, as `fae adapt` finds it: +y and +z in the scan's frame
    for axis, whole in ((1, np.array([-0.0774, 0.9713, 0.2249])), (2, np.array([-0.558, -0.2291, 0.7976]))):
        found = model.scan_transform[:3, axis] / np.linalg.norm(model.scan_transform[:3, axis])
        assert np.degrees(np.arccos(np.clip(found @ whole, -1.0, 1.0))) < 15.0, axis
    assert facemodel_problems(model) == []


@needs_mediapipe
def test_a_head_that_is_not_whole_is_not_written(bust, tmp_path, capsys, monkeypatch):
    """fae adapt checks the head it made as `fae template check` does (skin inside a bone,
    a bone through the skin, the skin through itself) and writes none that fails, unless
    told to with --force. The check is the anatomy's own (tested on its own); here a
    fit of the suite's bust is made to fail it."""
    import fae.anatomy.checks

    scan = tmp_path / "bust.obj"
    trimesh.Trimesh(bust.vertices, bust.faces, process=False).export(scan)
    problem = "skin: 3 skin vertices lie inside the mandible (first: vertex 2198)"
    monkeypatch.setattr(fae.anatomy.checks, "facemodel_problems", lambda model: [problem])
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 2
    err = capsys.readouterr().err
    assert "not whole" in err and "inside the mandible" in err and "--force" in err
    assert not out.exists()
    assert any("inside the mandible" in v for v in json.loads(rep.read_text())["verdict"])
    assert main(["adapt", str(scan), "-o", str(out), "--no-calibrate", "--force"]) == 0
    assert out.exists()


@needs_mediapipe
@pytest.mark.slow
def test_a_noisy_bust_with_a_hole_in_the_cheek_gives_a_whole_head_or_an_error(bust, template, tmp_path, capsys):
    V = np.asarray(bust.vertices, float).copy()
    F = np.asarray(bust.faces)
    mesh = trimesh.Trimesh(V, F, process=False)
    rng = np.random.default_rng(11)
    V += mesh.vertex_normals * rng.normal(scale=0.4, size=(len(V), 1))  # 0.4 mm of scanner noise
    cheek = bust.landmarks["5.3"] if "5.3" in bust.landmarks else bust.landmarks["8.3"]
    holed = np.linalg.norm(V[F].mean(axis=1) - cheek, axis=1) > 12.0  # a 12 mm hole in the cheek
    scan = tmp_path / "holed.obj"
    trimesh.Trimesh(V, F[holed], process=False).export(scan)
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    eyes = json.loads(rep.read_text())["eye_scale"]
    assert min(eyes.values()) > 0.9, eyes  # moved out of the tissue it crossed, not shrunk (0.71 once)
    report = json.loads(rep.read_text())
    assert report["folded_triangles"]["all"] == 0
    assert facemodel_problems(read_facemodel(out)) == []
    # the hole is filled from its surroundings: the skin there stays near the true cheek
    model = read_facemodel(out)
    S = np.linalg.inv(bust.to_scan) @ model.scan_transform
    skin = apply_transform(S, model.skin_vertices)
    truth_cheek = apply_transform(np.linalg.inv(bust.to_scan), np.asarray(cheek)[None])[0]
    near = np.linalg.norm(skin - truth_cheek, axis=1) < 0.012
    d = trimesh.proximity.closest_point(trimesh.Trimesh(bust.truth_vertices, bust.truth_faces, process=False),
                                        skin[near])[1]
    assert near.sum() > 10 and np.sqrt(np.mean(d ** 2)) < 2e-3


def test_feature_points_far_from_the_scan_are_refused_with_a_reason(tmp_path, capsys):
    scan, lm = tmp_path / "ball.obj", tmp_path / "lm.json"
    trimesh.creation.icosphere(subdivisions=3, radius=0.1).export(scan)
    names = ["3.5", "3.6", "9.3", "2.1", "8.3", "8.4", "11.1", "10.9"]
    rng = np.random.default_rng(0)
    lm.write_text(json.dumps({n: (100.0 + rng.normal(size=3)).tolist() for n in names}))  # 100 m away
    out = tmp_path / "head.glb"
    assert main(["adapt", str(scan), "--landmarks", str(lm), "-o", str(out), "--no-calibrate"]) == 2
    err = capsys.readouterr().err
    assert "feature points" in err and not out.exists()


@needs_mediapipe
@pytest.mark.slow
def test_the_menpo_face_with_its_ibug_points_is_fitted_over_the_face(shared_data, tmp_path):
    face = shared_data / "heads" / "menpo3d_template"
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(face / "template.ply"), "--landmarks", str(face / "template.ljson"), "-o", str(out),
                 "--report", str(rep), "--no-calibrate"]) == 0
    report = json.loads(rep.read_text())
    assert report["folded_triangles"]["all"] == 0
    # 0.046 % of the diagonal (0.112 % while the lips by the mask's mouth slit paired nothing, 0.066 %
    # while the skin within 8 mm of its outline did)
    assert report["errors"]["face_to_scan_rms_rel"] < 0.001 and report["errors"]["face_coverage"] > 0.95
    assert len(report["landmarks_used"]) >= 35
    assert facemodel_problems(read_facemodel(out)) == []


@needs_mediapipe
@pytest.mark.slow
def test_a_face_only_scan_with_holes_and_some_feature_points(template, tmp_path):
    from fae.adapt.synthetic import template_scan
    from fae.adapt.transfer import visible_skin

    F = np.asarray(template.skin_faces, np.int64)
    fdp = {n: p for n, p in template.feature_point_positions().items() if template.feature_points[n].part == "skin"}
    scan = template_scan(template.skin_vertices, F, fdp, seed=7, subdivisions=1,
                         drop_faces=~visible_skin(template)[F].all(axis=1), face_only=True, holes=3)
    path, lm = tmp_path / "face.obj", tmp_path / "lm.json"
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(path)
    some = [n for n in ("3.7", "3.8", "3.11", "3.12", "9.3", "2.1", "8.3", "8.4", "10.9", "10.10")
            if n in scan.landmarks]
    assert len(some) >= 8
    lm.write_text(json.dumps({n: np.asarray(scan.landmarks[n]).tolist() for n in some}))
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(path), "--landmarks", str(lm), "-o", str(out), "--report", str(rep),
                 "--no-calibrate"]) == 0
    report = json.loads(rep.read_text())
    assert report["folded_triangles"]["all"] == 0
    # 0.026 % of the diagonal: its eye openings are holes, not its rim (0.140 % while the
    # lids, within 8 mm of them, paired nothing; 0.118 % with the mouth's slit a hole)
    assert report["errors"]["face_to_scan_rms_rel"] < 0.001 and report["errors"]["face_coverage"] > 0.8
    model = read_facemodel(out)
    assert facemodel_problems(model) == []
    # the crown the scan lacks keeps the template's shape at the face's size: the scalp lies
    # 0.31 % of the diagonal (RMS) from the truth's (1.19 %, up to 3.5 %, when the template's
    # back of the head, paired with the face's rim, pulled the start small)
    assert report["scan_covers_part_of_head"] is True
    skin = apply_transform(model.scan_transform, model.skin_vertices)
    truth = trimesh.Trimesh(apply_transform(scan.to_scan, scan.warp(np.asarray(template.skin_vertices))), F,
                            process=False)
    scalp = np.asarray(template.skin_region) == template.region_names.index("scalp")
    gap = trimesh.proximity.closest_point(truth, skin[scalp])[1]
    assert np.sqrt(np.mean(gap ** 2)) < 0.006 * np.linalg.norm(np.ptp(truth.vertices, axis=0))


@pytest.mark.slow
def test_the_head_is_found_in_a_bust_lying_upside_down(template, bust):
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_euler("xyz", [20.0, 150.0, 70.0], degrees=True).as_matrix()
    V = np.asarray(bust.vertices) @ turn.T
    head = find_head(template, V, bust.faces)
    assert head.trusted
    R_true = turn @ bust.to_scan[:3, :3] / np.cbrt(np.linalg.det(bust.to_scan[:3, :3]))
    R_found = head.template_to_scan[:3, :3] / np.cbrt(np.linalg.det(head.template_to_scan[:3, :3]))
    angle = np.degrees(np.arccos(np.clip((np.trace(R_true.T @ R_found) - 1) / 2, -1, 1)))
    assert angle < 5.0


def test_skin_a_face_scan_does_not_reach_keeps_the_starts_shape(template):
    """The skin far from the scan takes the harmonic extension of the fit's displacement.
    Extended from the template's own place, the start's turn and scale went with it through
    the graph Laplacian's weights, which do not carry a linear field: on a face scan 1.25x
    the template and turned 12 degrees, the back of the head and the neck moved a median
    24 mm (up to 32) from where the start put them, the neck swung forward, and the blends
    that took back its folds left ridges on the crown. From the start: 2.4 (6.8) mm."""
    from fae.adapt.calibration import apply_transform
    from fae.adapt.transfer import visible_skin
    from fae.linalg import axis_angle

    P = np.asarray(template.skin_vertices, np.float64)
    F = np.asarray(template.skin_faces, np.int64)
    seen = visible_skin(template)
    front = seen & (P[:, 2] > np.percentile(P[:, 2], 55))
    M = np.eye(4)
    M[:3, :3] = 1.25 * axis_angle([0.3, 1.0, 0.1], np.radians(12.0))
    M[:3, 3] = [0.004, -0.01, 0.02]
    fit = fit_to_scan(P, F, surface(*kept_part(apply_transform(M, P), F, front)), seen)
    assert fit.partial_scan and fit.folded == 0
    region = np.asarray(template.skin_region)
    back = np.isin(region, [template.region_names.index(r) for r in ("scalp", "neck")])
    back &= P[:, 2] < np.percentile(P[:, 2], 30)
    moved = np.linalg.norm(fit.vertices[back] - apply_transform(fit.affine, P)[back], axis=1)
    assert np.median(moved) < 0.006 and moved.max() < 0.012, (np.median(moved), moved.max())


@needs_mediapipe
@pytest.mark.slow
def test_a_face_scan_in_millimetres_gives_a_whole_head_of_its_size(template, shared_data, tmp_path, capsys):
    """The meshmonk face (a face alone, eyes shut, in millimetres, no feature points): the
    search placed the template's head at 1/1.6 of its size, the unit was taken as none and
    the head came out 1.6x life size (FAPU 1.59x the template's), with ridges and a knob on
    the crown the scan does not reach, and `fae adapt` refused it (skin inside the
    cranium). The face found, 1.63x the size of that pose, places the head again: the unit
    is millimetres, the head the scan's size (0.86x the template, as its eye corners are
    0.89x), and the back of the head keeps the template's shape (a similarity from the
    template's to it leaves 0.5 mm RMS, 1.8 mm at most; 1.8 and 40 mm before)."""
    from fae.adapt.calibration import similarity_transform

    scan = shared_data / "heads" / "meshmonk_template" / "Template.obj"
    out, rep = tmp_path / "head.glb", tmp_path / "r.json"
    assert main(["adapt", str(scan), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    assert "the head is placed by the face" in capsys.readouterr().err
    report = json.loads(rep.read_text())
    assert report["scan_unit"] == "mm" and 0.75 < report["fapu_ratio"] < 1.0, report["fapu_ratio"]
    assert report["folded_triangles"]["all"] == 0 and report["scan_covers_part_of_head"] is True
    # 0.089 % of the diagonal (0.20 mm) over 86 % of the face (0.187 % while the skin within
    # 8 mm of its outline paired nothing: nonrigid.PARTIAL_EDGE_REACH); the face-landmark
    # model's points move it by a few hundredths from one of its versions to another
    assert report["errors"]["face_to_scan_rms_rel"] < 0.0012 and report["errors"]["face_coverage"] > 0.8
    model = read_facemodel(out)
    assert facemodel_problems(model) == []
    P, X = np.asarray(template.skin_vertices), np.asarray(model.skin_vertices)
    region = np.asarray(template.skin_region)
    back = np.isin(region, [template.region_names.index(r) for r in ("scalp", "neck")])
    back &= P[:, 2] < np.percentile(P[:, 2], 30)
    s, R, t = similarity_transform(P[back], X[back])
    residual = np.linalg.norm(s * P[back] @ R.T + t - X[back], axis=1)
    assert residual.max() < 0.02 * np.ptp(X, axis=0).max(), residual.max()


@pytest.mark.parametrize("shift", [(0.0, -0.015, -0.010), (0.0, -0.045, 0.0)], ids=["near", "4.5 cm down"])
def test_an_ear_is_found_where_the_scan_has_it(template, shift):
    """Ears are found by their shape: the template's left ear moved 15 mm down and 10 mm
    back, or 4.5 cm down (where a marble bust has its ears), on the 'scan' gives pairs that
    carry the template's ear there."""
    from fae.adapt.ears import ear_pairs
    from fae.adapt.errors import surface

    V = np.asarray(template.skin_vertices, float).copy()
    F = np.asarray(template.skin_faces, np.int64)
    ear = np.asarray(template.skin_region) == template.region_names.index("ear_l")
    shift = np.array(shift)
    V[ear] += shift
    pairs, report = ear_pairs(template, surface(V, F))
    assert report["ear_l"]["found"], report
    assert abs(report["ear_l"]["moved_m"] - np.linalg.norm(shift)) < 0.005
    assert report["ear_r"]["found"] and report["ear_r"]["moved_m"] < 0.002  # the right ear stays
    faces, bary, points = pairs
    on_template = np.einsum("kj,kjd->kd", bary, np.asarray(template.skin_vertices)[F[faces]])
    left = on_template[:, 0] > 0
    assert left.sum() >= 10
    error = np.linalg.norm(points[left] - on_template[left] - shift, axis=1)
    assert np.median(error) < 0.002 and np.quantile(error, 0.9) < 0.004, np.sort(error)


@needs_mediapipe
@pytest.mark.slow
def test_a_small_head_in_a_known_unit_keeps_its_pose_and_unit(template, bust, tmp_path, capsys):
    """The suite's bust scaled 0.72x in millimetres: a head 0.79x the template's, placed
    right. Its face found, 0.79x the template's face, read as a pose 1.29x off in size
    placed the head again (the marble bust scaled 0.78x in metres so lost its unit and came
    out 1.3x the person's size). Where the unit is known, the face frame has the person's
    size: the face's size is the person's, not the pose's error."""
    path, out, rep = tmp_path / "small.obj", tmp_path / "head.glb", tmp_path / "r.json"
    trimesh.Trimesh(np.asarray(bust.vertices) * 0.72, bust.faces, process=False).export(path)
    assert main(["adapt", str(path), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    assert "placed by the face" not in capsys.readouterr().err
    report = json.loads(rep.read_text())
    assert report["scan_unit"] == "mm" and 0.75 < report["fapu_ratio"] < 0.84, report["fapu_ratio"]
    assert report["confidence"]["head_placed_by"] == "searched"
    assert report["errors"]["face_to_scan_rms_rel"] < 0.0005


@pytest.mark.parametrize("placed", [False, True], ids=["as it is", "placed"])
@pytest.mark.parametrize("cut, found", [(40, True), (50, False), (55, False)])
def test_the_rim_of_a_front_half_is_not_taken_for_an_ear(template, cut, found, placed):
    """The template's front (skin in front of the cut, a percentile of its depth): cut
    behind the ears, they are found where they are; cut at them, the rim seen from the
    side stands out like an ear and was taken for one 5.5-6.6 cm from the template's, which
    then carried its ears there. On a scan of part of the head, an ear found farther than
    PARTIAL_SCAN_EAR_REACH from the template's is its rim."""
    from fae.adapt.ears import ear_pairs
    from fae.adapt.errors import surface
    from fae.adapt.nonrigid import covers_part_of_head
    from fae.adapt.transfer import visible_skin

    P = np.asarray(template.skin_vertices, np.float64)
    F = np.asarray(template.skin_faces, np.int64)
    seen = visible_skin(template)
    scan = surface(*kept_part(P, F, seen & (P[:, 2] > np.percentile(P[:, 2], cut))))
    assert covers_part_of_head(P[seen], scan)
    placement = None
    if placed:  # as adapt searches: at the template's size, where the fit's start places it
        from fae.adapt.nonrigid import start_placement

        points = [(fp.triangle, np.asarray(fp.bary)) for name, fp in template.feature_points.items()
                  if fp.part == "skin" and not name.startswith("10.")]
        faces, bary = np.array([f for f, _ in points]), np.array([b for _, b in points])
        placement, partial = start_placement(P, F, scan, seen, (faces, bary, np.einsum("kj,kjd->kd", bary, P[F[faces]])))
        assert partial
    pairs, report = ear_pairs(template, scan, partial=True, placement=placement)
    for side in ("ear_l", "ear_r"):
        assert report[side]["found"] == found, report
        if found:
            assert report[side]["moved_m"] < 0.002
        else:
            assert "rim" in report[side]["why"]
    assert (pairs is not None) == found
    # a whole head's ear may stand out that far from the template's (a marble bust's low ears)
    assert ear_pairs(template, scan, partial=False, placement=placement)[1]["ear_l"]["found"]


@needs_mediapipe
@pytest.mark.slow
def test_a_front_half_cut_at_the_ears_is_fitted_without_them(template, tmp_path):
    """The suite's warped template, its front half cut at the ears: the rims, taken for
    ears 6.4 and 6.9 cm from the template's, drew the template's ears there and swelled
    the jaw and neck (scan->skin 0.347 % of the diagonal, 1.26 % counting every point; the
    head 0.95x the truth's size). Now no ear is found there: 0.139 %, 0.28 %, 1.0x."""
    from fae.adapt.synthetic import template_scan
    from fae.adapt.transfer import visible_skin

    P = np.asarray(template.skin_vertices, np.float64)
    F = np.asarray(template.skin_faces, np.int64)
    fdp = {n: p for n, p in template.feature_point_positions().items() if template.feature_points[n].part == "skin"}
    front = visible_skin(template) & (P[:, 2] > np.percentile(P[:, 2], 50))
    scan = template_scan(P, F, fdp, seed=5, subdivisions=1, drop_faces=~front[F].all(axis=1), max_angle=0.3)
    path, out, rep = tmp_path / "front.obj", tmp_path / "head.glb", tmp_path / "r.json"
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(path)
    assert main(["adapt", str(path), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    report = json.loads(rep.read_text())
    assert report["scan_covers_part_of_head"] is True
    assert not report["ears"]["ear_l"]["found"] and not report["ears"]["ear_r"]["found"]
    errors = report["errors"]
    assert errors["scan_to_skin_rms_rel"] < 0.002 and errors["scan_to_skin_all_rms_rel"] < 0.004, errors
    assert errors["face_to_scan_rms_rel"] < 0.001
    assert report["scan_unit"] == "mm" and abs(report["fapu_ratio"] - 1.0) < 0.03


@pytest.mark.parametrize("size, cut", [(0.8, 40), (0.85, 40), (1.35, 0)], ids=["0.8x front", "0.85x front", "1.35x whole"])
def test_ears_are_found_on_a_head_of_another_size(template, size, cut):
    """The template scaled (0.8x or 0.85x, cut behind the ears as a front half; 1.35x whole),
    its face's feature points given: the ears are looked for at the template's size, where
    the fit's start places them, and their pairs land where the scaled ears are, as they do
    at 1x. Searched on the scan as it is, the small halves' ears were not found and the
    large head's pairs lay 11 mm off (median)."""
    from fae.adapt.ears import ear_pairs
    from fae.adapt.errors import surface
    from fae.adapt.nonrigid import start_placement
    from fae.adapt.transfer import visible_skin

    P = np.asarray(template.skin_vertices, np.float64)
    F = np.asarray(template.skin_faces, np.int64)
    seen = visible_skin(template)
    keep = seen & (P[:, 2] > np.percentile(P[:, 2], cut)) if cut else np.ones(len(P), bool)
    scan = surface(*kept_part(P * size, F, keep))
    points = [(fp.triangle, np.asarray(fp.bary)) for name, fp in template.feature_points.items()
              if fp.part == "skin" and not name.startswith("10.")]  # the face's, no ears
    faces, bary = np.array([f for f, _ in points]), np.array([b for _, b in points])
    placement, partial = start_placement(P, F, scan, seen, (faces, bary, size * np.einsum("kj,kjd->kd", bary, P[F[faces]])))
    assert partial == bool(cut)
    pairs, report = ear_pairs(template, scan, partial, placement)
    assert report["ear_l"]["found"] and report["ear_r"]["found"], report
    on_template = np.einsum("kj,kjd->kd", pairs[1], P[F[pairs[0]]])
    error = np.linalg.norm(pairs[2] - size * on_template, axis=1)
    # (on a front half some ear points lie past the cut: their pairs are the scan nearest, as at 1x)
    assert np.median(error) < 0.0005 and np.quantile(error, 0.9) < 0.004 * size, np.sort(error)[-5:]
    # the old search, on the scan as it is, found less or placed worse
    old_pairs, old = ear_pairs(template, scan, partial)
    if old_pairs is not None:
        old_on = np.einsum("kj,kjd->kd", old_pairs[1], P[F[old_pairs[0]]])
        assert np.median(np.linalg.norm(old_pairs[2] - size * old_on, axis=1)) > 0.003
    else:
        assert not old["ear_l"]["found"]


def test_a_head_with_no_ears_stands_out_has_none_found(template):
    """A head whose sides are smooth (the template's ears cut away and the holes left) has
    no ear to find: no pairs, and the report says why for each side."""
    from fae.adapt.ears import ear_pairs
    from fae.adapt.errors import surface

    F = np.asarray(template.skin_faces, np.int64)
    region = np.asarray(template.skin_region)
    ears = np.isin(region, [template.region_names.index("ear_l"), template.region_names.index("ear_r")])
    pairs, report = ear_pairs(template, surface(template.skin_vertices, F[~ears[F].any(axis=1)]))
    assert pairs is None
    assert not report["ear_l"]["found"] and not report["ear_r"]["found"]


@needs_mediapipe
@pytest.mark.slow
def test_a_bust_whose_ears_sit_low_gets_its_ears_where_the_scan_has_them(template, tmp_path):
    """The suite's bust with its left ear 4.5 cm lower than the template's (a marble bust's
    ears sit so): the adapted head's left ear lies on the scan's, not on the scalp above."""
    V = np.asarray(template.skin_vertices, float).copy()
    ear = np.asarray(template.skin_region) == template.region_names.index("ear_l")
    V[ear] += [0.0, -0.045, 0.0]
    scan = template_bust(template, V=V)
    path, out, rep = tmp_path / "bust.obj", tmp_path / "head.glb", tmp_path / "report.json"
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(path)
    assert main(["adapt", str(path), "-o", str(out), "--report", str(rep), "--no-calibrate"]) == 0
    report = json.loads(rep.read_text())
    assert report["ears"]["ear_l"]["found"], report["ears"]
    # the ear's free part (its root is stretched over the 4.5 cm on the scan)
    from scipy.spatial import cKDTree

    P = np.asarray(template.skin_vertices)
    free = np.flatnonzero(ear)[cKDTree(P[~ear]).query(P[ear])[0] > 0.008]
    head = read_facemodel(out)
    fitted = apply_transform(head.scan_transform, head.skin_vertices[free])  # the scan's frame
    truth = apply_transform(scan.to_scan, scan.warp(V[free]))
    error = np.linalg.norm(fitted - truth, axis=1) * 1e-3  # the scan is in mm
    assert len(free) > 50 and np.median(error) < 0.004, (len(free), np.median(error))


def test_the_workflow_refuses_what_it_cannot_trust_without_the_command_line(template):
    """fae.adapt.workflow works as a library: a plate is no head, and a scan nothing can look
    at is refused unless feature points stand in for the face-landmark model."""
    from fae.adapt.workflow import AdaptRefused, FacePairsUnavailable, adapt_scan

    plate = trimesh.creation.box(extents=(0.3, 0.02, 0.3)).subdivide().subdivide().subdivide()
    with pytest.raises(AdaptRefused, match="plate.obj: could not find a head .* give feature points"):
        adapt_scan(template, np.asarray(plate.vertices), np.asarray(plate.faces), lambda V, F: None,
                   scan_name="plate.obj")

    def blind(V, F):
        raise FacePairsUnavailable("nothing to draw with", fatal=True)

    head = np.asarray(template.skin_vertices) * 1000.0  # a scan in mm: the template itself
    with pytest.raises(AdaptRefused, match="nothing to draw with"):
        adapt_scan(template, head, np.asarray(template.skin_faces), blind)


@needs_mediapipe
@pytest.mark.slow
def test_an_adapted_bust_plays_expressions_as_cleanly_as_the_shipped_head(bust, template, tmp_path):
    """The suite's bust adapted and calibrated, then fap_streams/expressions.fap played on it
    and on the shipped head: the adapted skin folds or creases at most 1.3 times the
    template's own and 30 more (63 against 30 triangles measured: forehead 32 against 24 under anger's
    lowered brows, the cheeks 9 the template lacks, the lower lip 8; 57 against 35 before
    the lower lids' caps were merged away: the template lost its lower lids' few, the
    adapted head had none there and gained 6 on its forehead, cheeks and lip, the
    calibration's noise; 85 against 57 before the caps along the lower lip's
    inner rim were merged away, 82 before the eyes' rest gaze was
    turned through their openings' middles: three triangles' noise; 83 against 70 before
    the shipped head's lips and lids folded less), turns over as few (0 against 0),
    stretches no further (2.53x against 2.52x) and lets the lips cross in no more frames
    (30 against 33); and its feature points move as the standard asks (verify-faps)."""
    from fae.animate.player import Player, playable_head
    from fae.animate.skin_check import check_stream
    from fae.io.fap import read_fap

    scan, out = tmp_path / "bust.obj", tmp_path / "head.glb"
    trimesh.Trimesh(bust.vertices, bust.faces, process=False).export(scan)
    assert main(["adapt", str(scan), "-o", str(out)]) == 0
    stream = "fap_streams/expressions.fap"
    own, adapted = (check_stream(Player(playable_head(face)), read_fap(stream), stream)
                    for face in (template, read_facemodel(out)))
    assert adapted["triangles_folded"] <= 1.3 * own["triangles_folded"] + 30, (adapted, own)
    assert adapted["triangles_turned"] <= 2 * own["triangles_turned"] + 4, (adapted, own)
    assert adapted["max_stretch"] <= 1.15 * own["max_stretch"], (adapted, own)
    assert adapted["frames_lips_crossed"] <= own["frames_lips_crossed"] + 5, (adapted, own)
    report = verify_faps(Player(playable_head(read_facemodel(out))))
    assert passed_fraction(report) >= 0.9, [(r["fap"], round(r["ratio"], 2)) for r in report if not r["ok"]]


@pytest.fixture(scope="module")
def demosthenes(shared_data, tmp_path_factory):
    """The Demosthenes bust adapted and calibrated by `fae adapt`."""
    pytest.importorskip("mediapipe")
    scan = shared_data / "heads" / "busts" / "demosthenes" / "demosthenes.obj"
    out = tmp_path_factory.mktemp("demosthenes") / "head.glb"
    assert main(["adapt", str(scan), "-o", str(out)]) == 0
    return read_facemodel(out)


@needs_mediapipe
@pytest.mark.slow
def test_a_real_busts_lower_lids_keep_their_back_hidden_as_a_smile_raises_them(shared_data, tmp_path):
    """xface_pride on the head adapted from the marble bust: its sculpted lower lids pressed
    their rim's lining against the lid's front, and as the cheeks rose the skin's back
    showed at the lower lids (2-5 mm^2 in 20 frames) until the lower lids' rim moved back
    behind the visible skin with the rest of their lining (fae.adapt.transfer.
    LINING_RIM_MOVED_REGIONS): 0-2 frames now over 3 mm^2."""
    from fae.animate.player import Player, playable_head
    from fae.animate.skin_check import check_stream
    from fae.io.fap import read_fap

    scan = shared_data / "heads" / "busts" / "marble_bust" / "marble_bust.obj"
    if not scan.is_file():
        pytest.skip("marble bust not in the shared data")
    out = tmp_path / "head.glb"
    assert main(["adapt", str(scan), "-o", str(out)]) == 0
    stream = shared_data / "fap" / "xface_pride.fap"
    report = check_stream(Player(playable_head(read_facemodel(out))), read_fap(stream), str(stream))
    assert report["frames_back_shown"] <= 5, report["frames_back_shown"]


@needs_mediapipe
@pytest.mark.slow
def test_a_calibrated_real_bust_moves_its_feature_points_as_the_standard_asks(demosthenes):
    """Demosthenes (the bust whose nose and lower lip snapped furthest between two settled
    states: 43 of 50 FAPs within 15 % before the calibration searched for the scale) adapted
    and calibrated: `fae verify-faps` passes at least 90 % of the FAPs."""
    from fae.animate.player import Player, playable_head

    report = verify_faps(Player(playable_head(demosthenes)))
    assert passed_fraction(report) >= 0.9, [(r["fap"], round(r["ratio"], 2)) for r in report if not r["ok"]]


@needs_mediapipe
@pytest.mark.slow
def test_a_real_bust_blinks_without_showing_its_lids_lining(demosthenes, shared_data):
    """xface_beg's blink (frames 28-38) on the head adapted from Demosthenes: its lids,
    fitted to the bust's sculpted eyes, stand 5-10 mm off the eyeballs, and as the blink
    reopened their lining rolled out through the front (139 mm^2 seen by its back; 7 then,
    specks along the margin: fae.sim.build.LINING_STANDOFF; none now). And the lids crease
    in few places: 27 triangles before the caps the fit left in the upper lids were flipped
    away (fae.adapt.transfer.fitted_caps_flipped), 12 after."""
    from fae.animate.player import Player, playable_head
    from fae.animate.skin_check import SkinCheck, in_head_frame
    from fae.io.fap import read_fap

    check = SkinCheck(demosthenes)
    player = Player(playable_head(demosthenes))
    seen, folded = [], np.zeros(len(demosthenes.skin_faces), dtype=bool)
    for frame in player.play(read_fap(shared_data / "fap" / "xface_beg.fap")):
        if 28 <= frame.index <= 38:
            result = check.frame(in_head_frame(frame.skin_vertices, frame.bone_transforms["head"]))
            seen.append(result.back_area)
            folded |= result.folded
        if frame.index > 38:
            break
    assert len(seen) == 11 and max(seen) <= 20e-6, seen
    assert folded.sum() <= 18, int(folded.sum())


@needs_mediapipe
def test_the_landmark_model_loads_without_matplotlib_and_leaves_it_loadable(tmp_path):
    """MediaPipe's drawing helpers import matplotlib.pyplot; fae loads MediaPipe without it
    (0.4 s of `fae adapt`) and a later import of matplotlib still gets the real one."""
    script = (
        "import sys, threading\n"
        "from fae.render.landmarks import preload_landmark_model, detect_points\n"
        "preload_landmark_model()\n"
        "[t.join() for t in threading.enumerate() if t.name == 'mediapipe-import']\n"
        "assert 'mediapipe' in sys.modules and 'matplotlib' not in sys.modules\n"
        "import numpy as np\n"
        "assert detect_points(np.full((64, 64, 3), 200, np.uint8)) is None\n"
        "import matplotlib\n"
        "matplotlib.use('Agg')\n"
        "import matplotlib.pyplot as plt\n"
        "plt.plot([0, 1]); plt.savefig(sys.argv[1])\n"
    )
    out = tmp_path / "plot.png"
    r = subprocess.run([sys.executable, "-c", script, str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 1000
