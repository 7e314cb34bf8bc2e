"""The standard's tables in fae.mpeg4: every row against the reference files, plus invariants."""

from __future__ import annotations

import re

import numpy as np
import pytest

from fae.mpeg4 import fapu as fapu_mod
from fae.mpeg4.faps import FAP_COUNT, FAPS, LIP_PARTNER_FAP, MASK_GROUPS, MIRROR_FAP, fap_by_name, fap_info, mirror_fap
from fae.mpeg4.fdps import FEATURE_POINTS, GROUP_SIZES, feature_point, mirror_point
from fae.mpeg4.highlevel import EXPRESSIONS, VISEMES, Expression, Viseme, expression_by_name, viseme_by_name


def _tsv_rows(path):
    return [line.rstrip("\n").split("\t") for line in path.read_text().splitlines()
            if line.strip() and not line.startswith("#")]


@pytest.fixture(scope="module")
def reference(shared_data):
    folder = shared_data.parent / "reference"
    if not folder.is_dir():
        pytest.skip("shared reference tables absent")
    return folder


# ---- cross-checks against /work/shared/reference ----------------------------------------
def test_every_fap_row_matches_the_reference_table(reference):
    rows = _tsv_rows(reference / "mpeg4_fap_table.tsv")
    assert len(rows) == FAP_COUNT
    for row in rows:
        info = fap_info(int(row[0]))
        assert info.name == row[1]
        assert info.description == row[2]
        assert info.group == int(row[6])
        assert info.quant_step == int(row[8])
        if info.number <= 2:
            assert info.fapu is None and row[3] == "na"
            continue
        assert info.fapu == row[3]
        assert info.bidirectional == (row[4] == "B")
        assert info.motion == row[5]
        expected_points = () if row[7].startswith("na") else tuple(p.strip() for p in row[7].split(","))
        assert info.feature_points == expected_points
        for column, got in ((9, info.i_range), (10, info.p_range)):
            text = row[column].split("(")[0].strip()
            magnitude = int(text.lstrip("+-"))
            assert got == ((-magnitude, magnitude) if text.startswith("+-") else (0, magnitude)), (info.number, column)


def test_every_feature_point_matches_the_reference_table(reference):
    rows = _tsv_rows(reference / "mpeg4_fdp_feature_points.tsv")
    assert [r[0] for r in rows] == [p.name for p in FEATURE_POINTS]
    for name, description, acting in rows:
        point = feature_point(name)
        assert point.description == description
        listed = sorted({int(n) for n in re.findall(r"\b(\d+)\b", acting.split("(")[0])}
                        | {int(n) for n in re.findall(r"(\d+)", acting.split("(")[1])} if "(" in acting else
                        {int(n) for n in re.findall(r"(?:^|, )(\d+) ", acting)})
        assert list(point.faps) == listed, name


def test_fapu_visemes_expressions_and_groups_match_the_reference_text(reference):
    text = (reference / "mpeg4_fapu_visemes_expressions.md").read_text()
    for viseme in VISEMES:
        assert re.search(rf"^\| {viseme.code} \| {re.escape(viseme.name)} \| {re.escape(viseme.phonemes)} \|", text, re.M)
    for expression in EXPRESSIONS:
        assert re.search(rf"^\| {expression.code} \| {expression.name} \| {re.escape(expression.description)} \|",
                         text, re.M)
    for group, (first, last) in MASK_GROUPS.items():
        assert re.search(rf"^\| {group} \| {first}-{last} \|", text, re.M)
    assert "mask_index {0,2,18,30,38,42,47,50,60,64,68}" in text
    boundaries = [0] + [last for _, (_, last) in sorted(MASK_GROUPS.items())]
    assert boundaries == [0, 2, 18, 30, 38, 42, 47, 50, 60, 64, 68]


# ---- invariants that need no reference files ---------------------------------------------
def test_counts_and_group_sizes():
    assert len(FAPS) == 68 and [f.number for f in FAPS] == list(range(1, 69))
    assert len(FEATURE_POINTS) == 84
    sizes = {}
    for point in FEATURE_POINTS:
        sizes[point.group] = sizes.get(point.group, 0) + 1
    assert [sizes[g] for g in range(2, 12)] == [14, 14, 6, 4, 4, 1, 10, 15, 10, 6] == [GROUP_SIZES[g] for g in range(2, 12)]
    covered = [n for first, last in MASK_GROUPS.values() for n in range(first, last + 1)]
    assert covered == list(range(1, 69))
    assert all(first <= info.number <= last for info in FAPS for first, last in [MASK_GROUPS[info.group]])


def test_every_fap_feature_point_exists_and_lists_the_fap():
    for info in FAPS:
        for name in info.feature_points:
            assert info.number in feature_point(name).faps


def test_feature_point_mirrors_are_involutions_with_opposite_sides():
    for point in FEATURE_POINTS:
        partner = feature_point(point.mirror)
        assert partner.mirror == point.name
        assert partner.group == point.group
        assert partner.side == -point.side
        assert (point.side == 0) == (point.mirror == point.name)
    assert mirror_point("2.4") == "2.5" and mirror_point("3.5") == "3.6" and mirror_point("2.1") == "2.1"
    assert mirror_point("3.7") == "3.12"  # outer eye corners, named by image side
    assert mirror_point("8.9") == "8.10" and mirror_point("9.15") == "9.15"


def test_mirror_pairs_follow_the_index_convention_except_the_eye_corners():
    for point in FEATURE_POINTS:
        if point.side == 0 or point.name in ("3.7", "3.8", "3.11", "3.12"):
            continue
        partner = feature_point(point.mirror)
        assert abs(partner.index - point.index) == 1, point.name


def test_left_faps_pair_with_right_faps_on_mirrored_points():
    assert len(MIRROR_FAP) == 46
    for number, partner in MIRROR_FAP.items():
        a, b = fap_info(number), fap_info(partner)
        assert MIRROR_FAP[partner] == number
        assert ("_l_" in a.name or "_lm" in a.name) != ("_l_" in b.name or "_lm" in b.name)
        assert a.fapu == b.fapu and a.group == b.group and a.quant_step == b.quant_step and a.i_range == b.i_range
        for pa, pb in zip(a.feature_points, b.feature_points):
            assert mirror_point(pa) == pb
        if a.direction is not None and a.direction[0] != 0 and not a.is_rotation:
            # horizontal motions mirror in x: both outward (stretch, puff) or both inward (squeeze)
            side_a = feature_point(a.feature_point).side
            side_b = feature_point(b.feature_point).side
            assert a.direction[0] * side_a == b.direction[0] * side_b
    for number in (3, 4, 5, 14, 15, 16, 17, 18, 43, 44, 45, 46, 47, 48, 49, 50, 51, 52, 63, 64):
        assert mirror_fap(number) == number


def test_inner_and_outer_lip_partners_share_unit_and_direction():
    assert len(LIP_PARTNER_FAP) == 20
    for number, partner in LIP_PARTNER_FAP.items():
        a, b = fap_info(number), fap_info(partner)
        assert a.fapu == b.fapu and a.motion == b.motion
        assert {a.group, b.group} == {2, 8}


def test_directions_are_unit_vectors_in_the_face_frame():
    assert fap_by_name("open_jaw").direction == (0.0, -1.0, 0.0)
    assert fap_by_name("stretch_l_cornerlip").direction == (1.0, 0.0, 0.0)  # face's left = +x
    assert fap_by_name("stretch_r_cornerlip").direction == (-1.0, 0.0, 0.0)
    assert fap_by_name("squeeze_l_eyebrow").direction == (-1.0, 0.0, 0.0)  # toward the midline
    assert fap_by_name("thrust_jaw").direction == (0.0, 0.0, 1.0)
    assert fap_by_name("head_yaw").rotation_axis == (0.0, 1.0, 0.0)
    assert fap_by_name("head_pitch").rotation_axis == (1.0, 0.0, 0.0)
    for info in FAPS[2:]:
        if info.direction is not None:
            assert np.isclose(np.linalg.norm(info.direction), 1.0)
        assert (info.rotation_axis is not None) == (info.is_rotation and info.number != 47)


def test_value_range_is_the_i_range_times_the_quantiser_step():
    assert fap_info(48).value_range == (-316200.0, 316200.0)
    assert fap_info(3).value_range == (-4320.0, 4320.0)
    assert fap_info(19).value_range == (-1080.0, 1080.0)


def test_lookups_reject_bad_keys():
    for bad in (0, 69, -1, 1.0, True, "3"):
        with pytest.raises(ValueError):
            fap_info(bad)
    with pytest.raises(KeyError, match="no FAP"):
        fap_by_name("open_mouth")
    with pytest.raises(KeyError, match="group.index"):
        feature_point("12.1")


def test_visemes_and_expressions():
    assert len(VISEMES) == 15 and len(EXPRESSIONS) == 7
    assert viseme_by_name("PP").code == 1 and viseme_by_name("ou").code == 14
    assert [e.name for e in EXPRESSIONS] == ["neutral", "joy", "sadness", "anger", "fear", "disgust", "surprise"]
    assert expression_by_name("Surprise").code == 6
    (c1, w1), (c2, w2) = Viseme(10, 1, 63, 0).weights()
    assert (c1, w1, c2, w2) == (10, 1.0, 1, 0.0)
    assert Expression(1, 63, 3, 21, 0, 0).weights() == ((1, 1.0), (3, 1 / 3))


def _neutral_face_points():
    """A plausible adult neutral face in metres (face frame)."""
    return {
        "3.1": np.array([0.032, 0.0055, 0.080]), "3.3": np.array([0.032, -0.0055, 0.080]),
        "3.2": np.array([-0.032, 0.0056, 0.080]), "3.4": np.array([-0.032, -0.0054, 0.080]),
        "3.5": np.array([0.032, 0.0, 0.082]), "3.6": np.array([-0.032, 0.0, 0.082]),
        "9.15": np.array([0.0, -0.045, 0.095]), "2.2": np.array([0.0, -0.066, 0.092]),
        "8.3": np.array([0.025, -0.068, 0.080]), "8.4": np.array([-0.025, -0.068, 0.080]),
    }


def test_fapu_from_a_neutral_face():
    fapu0 = fapu_mod.fapu0_from_positions(_neutral_face_points())
    assert fapu0 == pytest.approx({"IRISD0": 0.011, "ES0": 0.064, "ENS0": 0.045, "MNS0": 0.021, "MW0": 0.050})
    fapu = fapu_mod.fapu_from_fapu0(fapu0)
    assert fapu["MNS"] == pytest.approx(0.021 / 1024) and fapu["AU"] == 1e-5
    # open_jaw 1024 MNS units drops the chin by one mouth-nose separation
    assert 1024 * fapu["MNS"] == pytest.approx(fapu0["MNS0"])


def test_fapu_errors_name_the_problem():
    points = _neutral_face_points()
    del points["9.15"]
    with pytest.raises(KeyError, match="9.15"):
        fapu_mod.fapu0_from_positions(points)
    points = _neutral_face_points()
    points["8.3"], points["8.4"] = points["8.4"], points["8.3"]  # left/right swapped
    with pytest.raises(ValueError, match="MW0"):
        fapu_mod.fapu0_from_positions(points)
    with pytest.raises(ValueError, match="ES0"):
        fapu_mod.fapu_from_fapu0({"IRISD0": 0.01, "ES0": -1, "ENS0": 0.04, "MNS0": 0.02, "MW0": 0.05})
