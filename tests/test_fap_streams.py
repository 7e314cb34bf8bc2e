"""The sample streams in fap_streams/: exactly what tools/make_fap_streams.py authors, and
they show what their README promises."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import astuple

import numpy as np

from fae.io.fap import read_fap
from fae.io.frames import dense_frames
from fae.mpeg4.faps import FAPS
from fae.mpeg4.highlevel import VISEMES


def test_the_tool_reproduces_the_shipped_files(repo_root, tmp_path):
    """Same header, frames and masks; each value within one FAP unit (the tool rounds
    smooth curves to integers, and another machine's last float digit may round the other
    way at a half)."""
    result = subprocess.run([sys.executable, str(repo_root / "tools" / "make_fap_streams.py"), str(tmp_path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    for name in ("expressions.fap", "visemes.fap", "eyes_head.fap", "all_faps_sweep.fap"):
        fresh, shipped = read_fap(tmp_path / name), read_fap(repo_root / "fap_streams" / name)
        assert fresh.header == shipped.header, name
        fresh, shipped = list(fresh), list(shipped)
        assert len(fresh) == len(shipped), name
        for a, b in zip(fresh, shipped):
            assert a.number == b.number and np.array_equal(a.mask, b.mask), f"{name} frame {b.number}"
            assert np.abs(a.values - b.values).max(initial=0) <= 1, f"{name} frame {b.number}"
            for x, y in ((a.viseme, b.viseme), (a.expression, b.expression)):
                assert (x is None) == (y is None), f"{name} frame {b.number}"
                if x is not None:  # selections exact, blend and intensities within one unit
                    assert np.abs(np.subtract(astuple(x), astuple(y))).max() <= 1, f"{name} frame {b.number}"
                    assert x.select1 == y.select1 and x.select2 == y.select2, f"{name} frame {b.number}"


def test_sweep_moves_every_low_level_fap_alone_through_its_range(repo_root):
    frames = list(read_fap(repo_root / "fap_streams" / "all_faps_sweep.fap"))
    values = np.array([d.values for d in dense_frames(frames, source_fps=25)])
    for info in FAPS[2:]:
        moving = np.flatnonzero(values[:, info.number - 1])
        assert moving.size, info.name
        segment = values[moving[0]:moving[-1] + 1]
        others = np.delete(segment, info.number - 1, axis=1)
        assert not others.any(), f"{info.name} does not move alone"
        low, high = info.value_range
        assert segment[:, info.number - 1].max() == high
        if info.bidirectional:
            assert segment[:, info.number - 1].min() == low
        else:  # unidirectional: 0 -> max -> 0 only
            assert segment[:, info.number - 1].min() > 0
        assert values[moving[-1] + 1, info.number - 1] == 0  # back to 0 before the next FAP


def test_visemes_spell_the_phrase(repo_root):
    frames = list(read_fap(repo_root / "fap_streams" / "visemes.fap"))
    names = []
    for frame in frames:
        name = VISEMES[frame.viseme.select1].name
        if not names or names[-1] != name or frame.viseme.blend == 32:
            names.append(name)
    assert names == ["sil", "TH", "aa", "nn", "kk", "ih", "ou", "sil", "PP", "oh", "PP", "sil"]


def test_expressions_are_six_distinct_poses_returning_to_neutral(repo_root):
    values = np.array([d.values for d in dense_frames(read_fap(repo_root / "fap_streams" / "expressions.fap"))])
    per = 55  # 2.2 s at 25 fps
    holds = values[[i * per + 25 for i in range(6)]]  # 1.0 s into each: held pose
    assert all(values[i * per + per - 1].any() == False for i in range(6))  # noqa: E712  neutral gaps
    # every pair of expressions differs clearly
    distances = [np.abs(holds[i] - holds[j]).max() for i in range(6) for j in range(i + 1, 6)]
    assert min(distances) >= 100
    joy, sadness, disgust = holds[0], holds[1], holds[4]
    assert joy[11] > 0 and joy[12] > 0 and sadness[11] < 0  # lip corners up in joy, down in sadness
    assert disgust[7] != disgust[8]  # the upper lip raised asymmetrically


def test_eyes_head_blinks_and_turns(repo_root):
    values = np.array([d.values for d in dense_frames(read_fap(repo_root / "fap_streams" / "eyes_head.fap"))])
    closed = values[:, 18] >= 1024
    assert np.count_nonzero(np.diff(closed.astype(int)) == 1) == 3  # three blinks
    assert np.array_equal(values[:, 22], values[:, 23])  # both eyes gaze together
    assert values[:, 48].max() > 24000 and values[:, 48].min() < -24000  # head turns 0.25 rad both ways
