"""FAP values -> clamped values -> simulation controls (fae.mpeg4.faptables.clamp_values,
fae.animate.controls.FapControls) on the synthetic head, calibrated without correction
passes: what the standard's ranges and the face's left/right symmetry require."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from fae.animate.calibrate import calibrate
from fae.animate.controls import ACTIVATION_LIMIT, JAW_ANGLE_LIMIT, ActivationLead, FapControls
from fae.mpeg4.faptables import FAP_LIMITS, clamp_values
from fae.animate.mapping import field_faps
from fae.mpeg4.faps import FAP_COUNT, FAPS, MIRROR_FAP
from fae.mpeg4.fdps import FEATURE_POINTS
from synthetic_head import synthetic_head

any_values = arrays(np.float64, FAP_COUNT, elements=st.floats(allow_nan=True, allow_infinity=True, width=64))
finite_values = arrays(np.float64, FAP_COUNT, elements=st.floats(-1e7, 1e7))
FAST = settings(max_examples=60, deadline=None)


@pytest.fixture(scope="module")
def head():
    return calibrate(synthetic_head(personalized=False, subdivisions=3, complete=False), passes=0)


@pytest.fixture(scope="module")
def controls(head):
    return FapControls(head)


def one_fap(fap: int, value: float) -> np.ndarray:
    v = np.zeros(FAP_COUNT)
    v[fap - 1] = value
    return v


@FAST
@given(any_values)
def test_clamped_values_lie_in_the_standard_ranges_and_clamping_twice_changes_nothing(values):
    once = clamp_values(values)
    assert np.all(np.isfinite(once))
    assert np.all((FAP_LIMITS[:, 0] <= once) & (once <= FAP_LIMITS[:, 1]))
    assert np.all(once[:2] == 0.0)  # the high-level FAPs are no low-level values
    assert np.array_equal(clamp_values(once), once)
    inside = np.isfinite(values) & (FAP_LIMITS[:, 0] <= values) & (values <= FAP_LIMITS[:, 1])
    inside[:2] = False
    assert np.array_equal(once[inside], values[inside])  # values in range are left alone


def test_clamping_follows_the_standard_table():
    v = clamp_values(np.full(FAP_COUNT, -1e12))
    for info in FAPS[2:]:
        low = v[info.number - 1]
        if info.bidirectional is False:
            assert low == 0.0, info.name  # unidirectional: nothing below neutral
        else:
            assert low < 0.0, info.name
    assert clamp_values(one_fap(3, 5000.0))[2] == 1080.0  # open_jaw: its I range in MNS
    assert clamp_values(one_fap(49, np.inf))[48] == FAPS[48].value_range[1]  # head_yaw: I range x quant step
    assert clamp_values(one_fap(49, np.nan))[48] == 0.0


@FAST
@given(finite_values)
def test_activations_and_jaw_are_bounded_for_any_values(controls, values):
    act, jaw = controls.controls(clamp_values(values))
    raw_act, raw_jaw = controls.controls(values)
    for a, j in ((act, jaw), (raw_act, raw_jaw)):
        assert np.all(np.isfinite(a)) and np.all(np.abs(a) <= ACTIVATION_LIMIT)
        assert np.all(a[: controls.model_muscles] >= 0.0)  # muscles only pull
        assert -0.05 <= j[0] <= JAW_ANGLE_LIMIT and -0.02 <= j[1] <= 0.03 and abs(j[2]) <= 0.03


def test_neutral_values_give_no_controls(controls):
    act, jaw = controls.controls(np.zeros(FAP_COUNT))
    assert not act.any() and not jaw.any()


def test_open_jaw_opens_the_jaw_monotonically_up_to_the_limit(controls):
    angles = [controls.controls(one_fap(3, v))[1][0] for v in np.linspace(0.0, 1080.0, 25)]
    assert angles[0] == 0.0 and angles[-1] > 0.0
    assert np.all(np.diff(angles) >= -1e-12)
    assert max(angles) <= JAW_ANGLE_LIMIT


def _mirror_permutation(head) -> np.ndarray:
    """Control index of each control's mirror partner: muscles _l <-> _r, the pull fields of
    mirror FAPs (a lowering field onto its mirror's), the midline ones onto themselves."""
    names = [m.name for m in head.muscles]
    swap = {"_l": "_r", "_r": "_l"}
    muscle = [names.index(n[:-2] + swap[n[-2:]] if n[-2:] in swap else n) for n in names]
    fields = field_faps(head)  # -k: the field of FAP k's negative values
    field = [len(names) + fields.index(int(np.copysign(MIRROR_FAP.get(abs(f), abs(f)), f))) for f in fields]
    return np.array(muscle + field)


@FAST
@given(fap=st.sampled_from(sorted(MIRROR_FAP)), fraction=st.floats(-1.0, 1.0))
def test_a_fap_and_its_mirror_drive_the_mirror_controls(head, controls, fap, fraction):
    """The synthetic head is mirror-symmetric, so a left FAP's controls, mirrored (left
    muscles for right ones, each pull field for its mirror FAP's), are its right partner's."""
    value = float(np.clip(fraction * 1000.0, *FAP_LIMITS[fap - 1]))
    act, jaw = controls.controls(one_fap(fap, value))
    mirror_act, mirror_jaw = controls.controls(one_fap(MIRROR_FAP[fap], value))
    scale = max(np.abs(act).max(), 1e-12)
    assert np.allclose(act[_mirror_permutation(head)], mirror_act, atol=1e-3 * scale)
    assert np.allclose(jaw, mirror_jaw, atol=1e-9)


def test_mirror_faps_are_left_right_pairs_moving_mirror_points():
    """Every sided FAP has its partner; a pair moves mirror feature points along mirrored
    directions (the eyeballs' yaw excepted: both gaze to the face's left, so that copying
    one eye's value to the other keeps the gaze conjugate)."""
    mirror_point = {p.name: p.mirror for p in FEATURE_POINTS}
    sided = [info for info in FAPS if any(w in info.name.split("_") for w in ("l", "r", "lm", "rm"))]
    assert {info.number for info in sided} == set(MIRROR_FAP)
    for fap, partner in MIRROR_FAP.items():
        a, b = FAPS[fap - 1], FAPS[partner - 1]
        assert MIRROR_FAP[partner] == fap
        assert [mirror_point[p] for p in a.feature_points] == list(b.feature_points), a.name
        if a.direction is None:
            continue
        expected = np.array(a.direction) if "yaw" in a.name else np.array(a.direction) * (-1.0, 1.0, 1.0)
        assert np.allclose(expected, b.direction), (a.name, b.name)


@FAST
@given(st.floats(-500, 500), st.floats(-500, 500), st.floats(0.0, 1.0))
def test_lip_twins_sent_alike_move_the_larger_requests_point_as_far_as_it_asks(inner, outer, overlap):
    """merge_lip_pairs: with each FAP moving its own point by its value and its twin's by
    overlap x value, the merged pair moves the point of the larger request by exactly that
    request; one FAP alone and twins of opposite signs are left as they are."""
    from fae.animate.controls import merge_lip_pairs

    v = np.zeros(FAP_COUNT)
    v[11], v[58] = inner, outer  # raise_l_cornerlip and raise_l_cornerlip_o
    c = np.zeros(FAP_COUNT)
    c[[11, 58]] = overlap
    m = merge_lip_pairs(v, c)
    assert np.array_equal(np.delete(m, [11, 58]), np.zeros(FAP_COUNT - 2))
    if inner * outer <= 0.0:
        assert m[11] == inner and m[58] == outer
    else:
        moved = (m[11] + overlap * m[58], m[58] + overlap * m[11])  # at 2.4, at 8.3
        big = 0 if abs(inner) >= abs(outer) else 1
        assert moved[big] == pytest.approx((inner, outer)[big], rel=1e-9)
        assert abs(moved[1 - big]) <= abs((inner, outer)[big]) * (1 + 1e-9)


def test_the_scale_search_closes_in_on_a_skin_that_snaps():
    """A response that jumps from 0.7x to 1.4x of the expected motion between two table
    scales (the skin snapping between two settled states): the calibration's search keeps
    trying scales strictly inside the bracket, so it ends as near the jump as it can."""
    from fae.animate.calibrate import _miss, _next_scale

    def response(scale):
        return 0.7 * scale / 2.0 if scale < 2.37 else 1.4 * scale / 2.5

    seen = [(2.0, response(2.0))]
    for _ in range(8):
        seen.append((s := _next_scale(seen), response(s)))
    short = max(s for s, r in seen if r < 1.0)
    over = min(s for s, r in seen if r > 1.0)
    assert short < 2.37 <= over and over - short < 0.03, seen
    # far from the bracket the step follows expected / measured, at most 2x
    assert _next_scale([(1.0, 0.1)]) == pytest.approx(2.0)
    # a smaller scale that overshot a larger one leaves no bracket: the search stops there
    assert _next_scale([(2.0, 0.8), (1.5, 1.3)]) is None
    assert _next_scale([(1.0, 0.8)]) == pytest.approx(1.25)
    assert _miss(0.8) == pytest.approx(0.25) and _miss(1.25) == pytest.approx(0.25) and _miss(-1.0) > 100


@pytest.mark.parametrize("mirrored", [False, True])
def test_a_lips_middle_fields_add_up_to_one_along_its_margin(mirrored):
    """lower_t_midlip (4) and lower_t_lip_lm (8) pull the upper lip's margin between 2.2 and
    2.6 with hats that add up to 1 there, and lower_t_lip_rm (9) not at all, whichever way
    the head's x runs; a corner's raise (12) keeps its round bump."""
    import copy

    from fae.animate.calibrate import MARGIN_SAMPLES, lip_margin_weight
    from fae.mpeg4.faptables import fapu_of
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel

    face = read_facemodel(shipped_head_path())
    radius = 0.16 * fapu_of(face)["ES"] * 1024.0
    if mirrored:  # x the face's right (not fae's face frame, whose FAPU it breaks)
        face = copy.deepcopy(face)
        face.skin_vertices = np.asarray(face.skin_vertices) * np.array([-1.0, 1.0, 1.0])
    w = {k: lip_margin_weight(face, k, radius) for k in (4, 8, 9, 12)}
    assert w[12] is None and all(w[k] is not None for k in (4, 8, 9))
    fp = face.feature_point_positions()
    V = np.asarray(face.skin_vertices)
    lip = np.flatnonzero(np.asarray(face.skin_region) == face.region_names.index("lip_upper"))
    along = fp["2.2"] + np.linspace(0.0, 1.0, MARGIN_SAMPLES)[1:-1, None] * (fp["2.6"] - fp["2.2"])
    margin = lip[np.argmin(np.linalg.norm(V[lip][None] - along[:, None], axis=2), axis=1)]
    total = w[4][margin] + w[8][margin]
    assert np.allclose(total, 1.0, atol=0.02) and np.all(w[9][margin] == 0.0)


def test_a_cheek_raise_pulls_the_lower_lid_half_as_hard_as_the_cheek():
    """lift_l_cheek (41) pulls with a round bump around its point, except on the lower
    eyelids, which it pulls half as hard: the cheek rising beneath pushes them the rest of
    the way, and pulled as hard their margin rolled off the eyeball."""
    from fae.animate.calibrate import (CHEEK_LID_SHARE, _FIELD_RADIUS_ES, _wendland, field_faps,
                                       geodesic_distance, pull_fields)
    from fae.mpeg4.faptables import FAP_FEATURE_POINT, fapu_of
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel

    face = read_facemodel(shipped_head_path())
    fapu = fapu_of(face)
    field = pull_fields(face, fapu)[field_faps(face).index(41)]
    radius = _FIELD_RADIUS_ES[41] * fapu["ES"] * 1024.0
    bump = _wendland(np.minimum(geodesic_distance(face, face.feature_points[FAP_FEATURE_POINT[40]], radius) / radius, 1.0))
    region = np.asarray(face.skin_region)
    lid = region == face.region_names.index("eyelid_lower_l")
    assert CHEEK_LID_SHARE == 0.5 and (bump[lid] > 0.05).sum() > 20  # the bump reaches the lid
    assert np.allclose(field.skin_weight[lid], CHEEK_LID_SHARE * bump[lid])
    assert np.allclose(field.skin_weight[~lid], bump[~lid])


def test_calibrating_again_drops_tables_baked_under_the_old_mapping():
    """A head's baked FaceDefTables are its simulation under its mapping: a head whose
    mapping is of an older format is calibrated again when loaded, and its baked tables,
    which the "fdt" engine would play as they were, go (authored ones stay)."""
    from fae.io.facemodel import FaceDefTable

    def table(source):
        return FaceDefTable(fap=4, part="skin", vertices=np.array([0], np.int32), borders=np.array([-1.0, 0.0, 1.0]),
                            displacements=np.zeros((2, 1, 3)), source=source)

    face = synthetic_head(personalized=False, subdivisions=3, complete=False)
    face.face_def_tables = [table("authored"), table("physics")]
    again = calibrate(face, passes=0)
    assert [t.source for t in again.face_def_tables] == ["authored"]


@FAST
@given(steps=st.lists(st.tuples(st.floats(-60.0, 60.0), st.floats(1e-300, 10.0)), min_size=1, max_size=12))
def test_a_led_pull_stays_finite_and_bounded_whatever_the_frame(steps):
    """ActivationLead on any activations and frame lengths (down to 1e-300 s, where the
    lead's 1 / (1 - e) is unbounded): every pull finite and within ACTIVATION_LIMIT."""
    lead = ActivationLead(np.array([0]), 0.045)
    for a, dt in steps:
        a = float(np.clip(a, -ACTIVATION_LIMIT, ACTIVATION_LIMIT))
        pull = lead.apply(np.array([a, 1.0]), dt)
        assert np.all(np.isfinite(pull)) and abs(pull[0]) <= ACTIVATION_LIMIT
        assert pull[1] == 1.0  # rows not led pass as they are


def test_a_lead_pulls_a_rise_so_a_lag_reaches_it_and_passes_a_fall():
    """A step of 0.3 in a 40 ms frame against a 45 ms lag is pulled 0.3 / (1 - e^(-40/45))
    (1.7x), then 0.3 once reached; a fall is passed as it is and the lag decays towards it."""
    lead = ActivationLead(np.array([0]), 0.045)
    gone = 1.0 - np.exp(-0.04 / 0.045)
    assert lead.apply(np.array([0.3]), 0.04)[0] == pytest.approx(0.3 / gone)
    assert lead.apply(np.array([0.3]), 0.04)[0] == pytest.approx(0.3)
    assert lead.apply(np.array([0.1]), 0.04)[0] == pytest.approx(0.1)
    assert lead.reached[0] == pytest.approx(0.1 + 0.2 * (1.0 - gone))
