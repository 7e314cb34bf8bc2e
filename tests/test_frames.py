"""Frame semantics: hold, fill, clamp, gaps, resampling, and the incremental FrameState."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fae.io.fap import FapFrame, Viseme, read_fap
from fae.io.frames import FrameState, dense_frames


def frame(number, sent: dict[int, float], viseme=None):
    mask = np.zeros(68, dtype=bool)
    values = np.zeros(68)
    for fap, value in sent.items():
        mask[fap - 1] = True
        values[fap - 1] = value
    return FapFrame(number, mask, values, viseme)


def test_unsent_faps_hold_their_last_value():
    frames = [frame(0, {3: 100, 48: 500}), frame(1, {3: 200}), frame(2, {48: -500}), frame(3, {})]
    dense = list(dense_frames(frames, source_fps=25))
    assert [d.values[2] for d in dense] == [100, 200, 200, 200]
    assert [d.values[47] for d in dense] == [500, 500, -500, -500]
    assert [d.index for d in dense] == [0, 1, 2, 3] and [d.time for d in dense] == [0, 0.04, 0.08, 0.12]
    assert not any(d.values[[0, 1, 3, 4]].any() for d in dense)  # never sent: neutral


def test_viseme_is_held_until_fap1_is_sent_again():
    frames = [frame(0, {1: 5}, Viseme(5, 0, 63, 0)), frame(1, {3: 10}), frame(2, {1: 1}, Viseme(1, 5, 32, 0))]
    dense = list(dense_frames(frames, source_fps=25))
    assert [d.viseme for d in dense] == [Viseme(5, 0, 63, 0), Viseme(5, 0, 63, 0), Viseme(1, 5, 32, 0)]


def test_fill_copies_the_mirror_then_the_lip_partner_only_when_asked():
    frames = [frame(0, {6: 150, 31: 200, 32: 50, 51: -60}), frame(1, {7: 90})]
    plain = list(dense_frames(frames, source_fps=25))
    filled = list(dense_frames(frames, source_fps=25, fill=True))
    assert plain[0].values[6] == 0 and plain[0].values[3] == 0
    assert filled[0].values[6] == 150  # stretch_r_cornerlip from stretch_l_cornerlip
    assert filled[0].values[31] == 50  # both eyebrows sent: nothing copied
    assert filled[0].values[3] == -60  # lower_t_midlip from lower_t_midlip_o
    assert filled[0].values[52] == 150  # stretch_l_cornerlip_o from its inner partner (no mirror sent)
    assert filled[1].values[5] == 90 and filled[1].values[6] == 90  # left from right now; right sent
    assert filled[1].values[3] == -60  # held


def test_values_outside_the_range_are_clamped_with_one_warning_per_fap():
    frames = [frame(0, {3: 5000, 48: 400000}), frame(1, {3: 6000}), frame(2, {3: -100, 48: 10})]
    dense_iter = dense_frames(frames, source_fps=25)
    dense = list(dense_iter)
    assert [d.values[2] for d in dense] == [4320, 4320, -100]  # open_jaw: 1080 x 4 MNS units
    assert [d.values[47] for d in dense] == [316200, 316200, 10]  # head_pitch: 1860 x 170 AU
    assert len(dense_iter.warnings) == 2
    assert "FAP 3 open_jaw = 5000" in dense_iter.warnings[0] and "FAP 48 head_pitch" in dense_iter.warnings[1]
    unclamped = list(dense_frames(frames, source_fps=25, clamp=False))
    assert unclamped[1].values[2] == 6000


def test_gaps_in_frame_numbers_are_filled_with_held_frames():
    frames = [frame(1, {3: 10}), frame(2, {3: 20}), frame(6, {3: 60})]
    dense = list(dense_frames(frames, source_fps=10))
    assert [d.index for d in dense] == [0, 1, 2, 3, 4, 5]
    assert [d.values[2] for d in dense] == [10, 20, 20, 20, 20, 60]
    assert dense[5].time == pytest.approx(0.5)


@pytest.mark.parametrize("fps", [50.0, 30.0, 12.5, 7.0, 25.0])
def test_resampling_keeps_the_duration_and_interpolates_linearly(fps):
    frames = [frame(k, {3: 10.0 * k}, Viseme(k % 15, 0, 63, 0) if k % 5 == 0 else None) for k in range(100)]
    for f in frames:
        if f.viseme is None:
            f.mask[0] = False
        else:
            f.mask[0] = True
            f.values[0] = f.viseme.select1
    dense = list(dense_frames(frames, source_fps=25, fps=fps))
    assert len(dense) == math.ceil(100 * fps / 25)  # 4 s of frames at the new rate
    assert dense[-1].time < 4.0 <= dense[-1].time + 1 / fps + 1e-9
    times = np.array([d.time for d in dense])
    assert np.allclose(np.diff(times), 1 / fps)
    expected = np.minimum(times * 25, 99) * 10.0  # linear ramp, held after the last frame
    assert np.allclose([d.values[2] for d in dense], expected)
    for d in dense:  # high-level records come from the nearest earlier source frame
        source = math.floor(d.time * 25 + 1e-9)
        assert d.viseme.select1 == (5 * (source // 5)) % 15


def test_frame_state_fed_one_frame_at_a_time_matches_dense_frames(shared_data):
    stream = read_fap(shared_data / "fap" / "xface_joy.fap")
    state = FrameState(fill=True)
    incremental = [state.update(f) for f in stream]
    batch = [d.values for d in dense_frames(stream, fill=True)]
    assert np.array_equal(np.array(incremental), np.array(batch))
    assert state.warnings == []


def test_shipped_expressions_play_for_13_seconds_and_stay_in_range(repo_root):
    stream = read_fap(repo_root / "fap_streams" / "expressions.fap")
    dense_iter = dense_frames(stream, fps=30)
    dense = list(dense_iter)
    assert dense_iter.warnings == []
    assert len(dense) == math.ceil(330 * 30 / 25) and dense[-1].time < 13.2
    values = np.array([d.values for d in dense])
    # neutral at the start and between expressions, clearly moving in each of the six holds
    assert not values[0].any()
    peaks = [np.abs(values[int((i * 2.2 + 1.0) * 30)]).max() for i in range(6)]
    assert min(peaks) >= 100


def test_bad_rates_are_rejected():
    with pytest.raises(ValueError, match="source_fps"):
        dense_frames([frame(0, {})])
    with pytest.raises(ValueError, match="output fps"):
        dense_frames([frame(0, {})], source_fps=25, fps=0)


def test_dense_frames_can_be_stepped_with_next_or_looped_again(repo_root):
    stream = read_fap(repo_root / "fap_streams" / "eyes_head.fap")
    dense = dense_frames(stream, fps=50)
    first, second = next(dense), next(dense)
    assert (first.index, second.index) == (0, 1) and second.time == pytest.approx(0.02)
    assert len(list(dense)) == len(list(dense)) == 500


def test_the_clamp_warning_names_the_range_the_face_plays():
    from fae.mpeg4.faptables import FAP_LIMITS

    state = FrameState(source_name="s.fap")
    state.update(frame(4, {3: 5000}))
    low, high = FAP_LIMITS[2]
    assert (low, high) == (0, 1080)  # open_jaw: what the Player clamps to
    assert state.warnings == ["s.fap: frame 4: FAP 3 open_jaw = 5000 MNS is outside [0, 1080], the range the face "
                              "plays; played as 1080 here and cut to that range wherever else it is outside"]
    state.update(frame(5, {3: -5}))  # a unidirectional FAP a little below 0, as real streams send
    quiet = FrameState()
    quiet.update(frame(0, {3: -5, 41: -4}))
    assert quiet.warnings == []


def test_a_gap_longer_than_max_hold_is_cut_with_one_warning():
    """Frames 0 and 10**12 are legal; their 10**12 held frames are not played: the hold is
    cut to max_hold seconds and the frames after it move up (resampled alike)."""
    frames = [frame(0, {3: 10}), frame(10 ** 12, {3: 20}), frame(10 ** 12 + 2, {3: 30})]
    dense = dense_frames(frames, source_fps=2, max_hold=3)
    out = list(dense)
    assert [d.index for d in out] == list(range(10)) and [d.values[2] for d in out] == [10] * 7 + [20, 20, 30]
    assert dense.warnings == ["<stream>: frames 1..999999999999 are missing (5e+11 s): frame 0 is held for 3 s only, "
                              "and the stream goes on from there"]
    assert len(list(dense_frames(frames, source_fps=2, max_hold=3, fps=4))) == 20
    assert len(list(dense_frames(frames[:1] + [frame(100, {3: 1})], source_fps=2, max_hold=None))) == 101
    assert len(list(dense_frames([frame(0, {}), frame(10 ** 12, {})], source_fps=25))) == 1502  # 60 s by default


@pytest.mark.parametrize("fps", [None, 4.0, 3.0, 0.7])
@pytest.mark.parametrize("max_hold", [3.0, None])
def test_count_is_the_length_of_a_pass_without_making_the_held_frames(fps, max_hold):
    """`count()` gives what a pass yields from the frame numbers alone: a gap of a trillion
    frames is counted at once (fae export refuses a scene too large before playing it)."""
    frames = [frame(0, {3: 10}), frame(5, {3: 20}), frame(40, {3: 30}), frame(41, {3: 40})]
    dense = dense_frames(frames, source_fps=2, fps=fps, max_hold=max_hold)
    assert dense.count() == len(list(dense))
    far = dense_frames([frame(0, {}), frame(10 ** 12, {})], source_fps=25, max_hold=None)
    assert far.count() == 10 ** 12 + 1
    assert dense_frames([], source_fps=25).count() == 0
