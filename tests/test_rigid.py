"""Rigid poses from FAP values (fae.animate.rigid.RigidRig) on the synthetic head: proper
rotations, rest at zero, continuous and monotone in each FAP over its range."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from fae.mpeg4.faptables import FAP_LIMITS, clamp_values, fapu_of
from fae.animate.rigid import RigidRig
from fae.linalg import axis_angle
from fae.mpeg4.faps import AU, FAP_COUNT, FAPS
from synthetic_head import synthetic_head

FAST = settings(max_examples=60, deadline=None)
ROTATION_FAPS = (23, 24, 25, 26, 48, 49, 50)  # eyeball yaw/pitch, head pitch/yaw/roll
BONE_OF = {23: "eye_l", 24: "eye_r", 25: "eye_l", 26: "eye_r", 48: "head", 49: "head", 50: "head"}
fap_values = arrays(np.float64, FAP_COUNT, elements=st.floats(-1e6, 1e6))


@pytest.fixture(scope="module")
def head():
    return synthetic_head(personalized=False, subdivisions=3, complete=False)


@pytest.fixture(scope="module")
def rig(head):
    return RigidRig(head, fapu_of(head))


def one_fap(fap: int, value: float) -> np.ndarray:
    v = np.zeros(FAP_COUNT)
    v[fap - 1] = value
    return v


def angle_of(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def assert_proper_rotation(T: np.ndarray) -> None:
    R = T[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


def test_zero_faps_and_a_closed_jaw_leave_every_bone_at_rest(rig):
    poses = rig.poses(np.zeros(FAP_COUNT), rig.jaw(0.0, 0.0, 0.0))
    assert set(poses) == {"head", "jaw", "eye_l", "eye_r", "tongue"}
    for name, T in poses.items():
        assert np.allclose(T, np.eye(4), atol=1e-15), name
    assert rig.pupil_scale(np.zeros(FAP_COUNT)) == {"eye_l": 1.0, "eye_r": 1.0}


@FAST
@given(values=fap_values, angle=st.floats(-0.05, 0.5), thrust=st.floats(-0.02, 0.03), shift=st.floats(-0.03, 0.03))
def test_head_eyes_and_jaw_move_rigidly(rig, values, angle, thrust, shift):
    v = clamp_values(values)
    poses = rig.poses(v, rig.jaw(angle, thrust, shift))
    for name in ("head", "jaw", "eye_l", "eye_r"):
        assert_proper_rotation(poses[name])
    # the eyes turn about their own centres (then thrust along the head's z)
    for k, name in enumerate(("eye_l", "eye_r")):
        eye = rig.eye(v, name)
        moved = eye[:3, :3] @ rig.eye_centers[name] + eye[:3, 3]
        assert np.allclose(moved - rig.eye_centers[name], [0.0, 0.0, v[26 + k] * rig.fapu["ES"]], atol=1e-12)
    # the head turns about 7.1: that point stays where it is
    H = poses["head"]
    assert np.allclose(H[:3, :3] @ rig.head_center + H[:3, 3], rig.head_center, atol=1e-12)


@pytest.mark.parametrize("fap", ROTATION_FAPS)
def test_a_rotation_fap_turns_its_bone_by_its_value_about_its_axis(rig, fap):
    """Angle = |value| AU about the standard's axis, continuous and monotone over the range."""
    info = FAPS[fap - 1]
    hi = min(FAP_LIMITS[fap - 1, 1], 0.99 * np.pi / AU)  # beyond pi the angle of a rotation wraps
    values = np.linspace(-hi, hi, 81)
    bone = BONE_OF[fap]
    poses = [rig.poses(one_fap(fap, x), rig.jaw(0.0, 0.0, 0.0))[bone] for x in values]
    angles = np.array([angle_of(T[:3, :3]) for T in poses])
    assert np.allclose(angles, np.abs(values) * AU, atol=1e-9)
    x = values[-1]
    assert np.allclose(poses[-1][:3, :3], axis_angle(np.array(info.rotation_axis), x * AU), atol=1e-12)
    steps = np.array([np.abs(b - a).max() for a, b in zip(poses, poses[1:])])
    assert steps.max() < 2.5 * (values[1] - values[0]) * AU  # continuous: no jump between neighbours


@pytest.mark.parametrize("fap, bone", [(23, "eye_l"), (24, "eye_r")])
def test_a_positive_yaw_turns_the_gaze_to_the_faces_left(rig, fap, bone):
    R = rig.poses(one_fap(fap, 20000.0), rig.jaw(0.0, 0.0, 0.0))[bone][:3, :3]
    gaze = R @ [0.0, 0.0, 1.0]
    assert gaze[0] > 0.1  # +x is the face's left (the standard's "left")


def test_opening_the_jaw_lowers_the_chin_monotonically(head, rig):
    chin = head.feature_point_positions()["2.1"]
    heights = []
    for angle in np.linspace(0.0, 0.5, 26):
        T = rig.jaw(angle, 0.0, 0.0)
        assert_proper_rotation(T)
        assert np.isclose(angle_of(T[:3, :3]), angle)
        heights.append((T[:3, :3] @ chin + T[:3, 3])[1])
    assert np.all(np.diff(heights) < 0.0)


def test_pupil_dilation_grows_the_pupil_and_never_inverts_it(rig):
    sizes = [rig.pupil_scale(one_fap(29, v))["eye_l"] for v in np.linspace(*FAP_LIMITS[28], 41)]
    assert np.all(np.diff(sizes) >= 0.0) and min(sizes) >= 0.05
    assert rig.pupil_scale(one_fap(29, 100.0))["eye_r"] == 1.0  # the left FAP leaves the right pupil


def test_the_shortest_turn_between_two_directions_is_capped_and_handles_opposites():
    from fae.linalg import turn_between

    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        R = turn_between(a, b)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-12)
        # about the common normal: that normal stays put
        n = np.cross(a, b)
        assert np.allclose(R @ n, n, atol=1e-12)
    for gap in (1e-11, 1e-9, 1e-7):  # nearly parallel: still onto b to the last digits
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        b = a + gap * np.cross(a, rng.normal(size=3))
        assert np.allclose(turn_between(a, b) @ a, b / np.linalg.norm(b), atol=1e-11)
    up = np.array([0.0, 1.0, 0.0])
    assert np.allclose(turn_between(up, -up) @ up, -up, atol=1e-12)
    assert np.allclose(turn_between(up, 3 * up), np.eye(3))
    tilted = np.array([0.0, np.cos(0.5), np.sin(0.5)])  # 28.6 degrees from up
    capped = turn_between(up, tilted, np.radians(10.0))
    assert np.isclose(np.degrees(np.arccos(capped[:, 1] @ up)), 10.0)
