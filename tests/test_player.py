"""Player invariants on a small calibrated head."""

from __future__ import annotations

import numpy as np
import pytest

from fae.animate.calibrate import calibrate
from fae.mpeg4.faptables import FAP_LIMITS
from fae.animate.player import Player, playable_head
from synthetic_head import synthetic_head

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def player():
    return Player(playable_head(calibrate(synthetic_head(personalized=False, subdivisions=4, complete=False), passes=0)))


def test_zero_faps_keep_the_face_at_rest(player):
    player.reset()
    for _ in range(100):
        skin = player.step(np.zeros(68), dt=1 / 25)
    assert np.abs(skin - player.face.skin_vertices).max() < 1e-5


def test_random_and_out_of_range_faps_stay_finite_and_return_to_rest(player):
    player.reset()
    rng = np.random.default_rng(0)
    for i in range(300):
        v = rng.uniform(FAP_LIMITS[:, 0], FAP_LIMITS[:, 1]) * (10.0 if i % 50 == 0 else rng.uniform(0, 1))
        skin = player.step(v, dt=1 / 25)
        assert np.all(np.isfinite(skin))
        H = player.bone_transforms["head"]
        in_head = (skin - H[:3, 3]) @ H[:3, :3]  # the head's own rotation is free
        assert np.abs(in_head - player.face.skin_vertices).max() < 0.08  # every FAP at once, full range
    for _ in range(50):
        skin = player.step(np.zeros(68), dt=1 / 25)
    assert np.abs(skin - player.face.skin_vertices).max() < 1e-4


def test_a_left_fap_moves_the_left_side_only(player):
    player.reset()
    v = np.zeros(68)
    v[52] = FAP_LIMITS[52, 1] / 2  # stretch_l_cornerlip_o
    for _ in range(30):
        skin = player.step(v, dt=1 / 25)
    d = np.linalg.norm(skin - player.face.skin_vertices, axis=1)
    x = player.face.skin_vertices[:, 0]
    assert d[x > 0].max() > 1e-3
    assert d[x < -0.01].max() < 0.15 * d[x > 0].max()


def test_players_of_one_head_share_its_arrays_and_step_independently(player):
    """Players of one PlayableHead share its static arrays but not their state: two streams
    on two players give what each gives alone, interleaved, and the first is left as it was."""
    player.reset()
    a, b = Player(player.head), Player(player.head)
    assert a.sim is player.sim and a.state is not b.state and a.control is not b.control
    va, vb = np.zeros(68), np.zeros(68)
    va[11] = 300.0  # raise_l_cornerlip
    vb[2] = 400.0   # open_jaw
    for _ in range(5):
        ska = a.step(va, dt=1 / 25)
        skb = b.step(vb, dt=1 / 25)
    alone = Player(player.head)
    for _ in range(5):
        ref = alone.step(va, dt=1 / 25)
    assert np.abs(ska - ref).max() < 1e-7
    assert np.abs(skb - ska).max() > 1e-3
    assert np.abs(player.step(np.zeros(68), dt=1 / 25) - player.face.skin_vertices).max() < 1e-6


def test_a_step_of_a_million_seconds_costs_what_one_second_costs(player):
    """A frame lasting 1e6 s (a gap in a stream, a tiny fps) simulates MAX_STEP_SECONDS of
    it: it returns at once with the pose one second of the frame gives; +inf lasts as long.
    Zero, negative and NaN durations are refused by name."""
    from fae.animate.player import MAX_STEP_SECONDS

    v = np.zeros(68)
    v[2] = FAP_LIMITS[2, 1] / 2  # open_jaw
    player.reset()
    one_second = player.step(v, dt=MAX_STEP_SECONDS)
    for dt in (1e6, float("inf")):
        player.reset()
        long_frame = player.step(v, dt=dt)  # 5e7 substeps if it were not bounded
        assert np.array_equal(long_frame, one_second)
    for dt in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="dt must be a positive number of seconds"):
            player.step(v, dt=dt)


def test_infinite_values_clamp_like_the_largest_finite_ones(player):
    for big in (np.inf, -np.inf):
        inf_values, huge_values = np.full(68, big), np.full(68, np.sign(big) * 1e308)
        assert np.array_equal(player.frame_values(inf_values), player.frame_values(huge_values))
    top = player.frame_values(np.full(68, np.inf))
    assert np.array_equal(top[2:], FAP_LIMITS[2:, 1])
    assert np.array_equal(player.frame_values(np.full(68, np.nan))[2:], np.zeros(66))


def test_only_a_mapping_for_this_solver_starts_a_calibration():
    """A personalized head's calibration starts from its template's table scales (one pass
    instead of three) only when they were measured with the same solver and layout."""
    from fae.animate.calibrate import warm_start_usable
    from fae.animate.mapping import FORMAT_VERSION

    good = {"layout": np.array([27, 40, 3, FORMAT_VERSION]), "table_scale": np.full((68, 5), 1.2),
            "jaw_follow": np.zeros(68), "hold_scale": np.ones(68)}
    assert warm_start_usable(good)
    assert not warm_start_usable(None) and not warm_start_usable({})
    assert not warm_start_usable({k: v for k, v in good.items() if k != "jaw_follow"})
    assert not warm_start_usable({**good, "layout": np.array([27, 40, 3, FORMAT_VERSION - 1])})
    assert not warm_start_usable({**good, "table_scale": np.full((60, 5), 1.2)})
    bad = good["table_scale"].copy()
    bad[3, 1] = np.nan
    assert not warm_start_usable({**good, "table_scale": bad})
