"""Writing .fap v2.1: read -> write -> read gives the same frames; writes are atomic."""

from __future__ import annotations

import numpy as np
import pytest

from fae.io.fap import FapFrame, FapHeader, read_fap, write_fap


def _roundtrip(path, tmp_path):
    stream = read_fap(path)
    frames = list(stream)
    out = tmp_path / ("copy_" + path.name)
    assert write_fap(out, stream.header, frames) == len(frames)
    again = read_fap(out)
    assert again.header.version == "2.1" and again.header.fps == stream.header.fps
    assert again.header.name == " ".join(stream.header.name.split())
    assert list(again) == frames and again.warnings == []
    return out


def test_shared_files_roundtrip(shared_data, tmp_path):
    for path in sorted((shared_data / "fap").glob("*.fap")):
        out = _roundtrip(path, tmp_path)
        # integers stay integers: the values lines are token-for-token the original's
        original = [line.split() for line in path.read_text().splitlines()[1:]]
        written = [line.split() for line in out.read_text().splitlines()[1:]]
        assert written == original


def test_shipped_streams_roundtrip(repo_root, tmp_path):
    for path in sorted((repo_root / "fap_streams").glob("*.fap")):
        _roundtrip(path, tmp_path)


def test_floats_highlevel_forms_and_gaps_roundtrip(tmp_path):
    mask = np.zeros(68, dtype=bool)
    mask[[0, 1, 2, 47]] = True
    values = np.zeros(68)
    values[[2, 47]] = [0.1, -12345.678901234567]
    from fae.io.fap import Expression, Viseme
    frames = [
        FapFrame(1, mask, values.copy(), Viseme(3, 4, 20, 1), Expression(2, 10, 5, 60, 1, 1)),
        FapFrame(4, mask, np.where(mask, [7, 2500.0] + [1e-7] * 66, 0.0), None, None),  # single tokens
    ]
    frames[0].values[[0, 1]] = [3, 2]
    out = tmp_path / "mixed.fap"
    write_fap(out, FapHeader("2.2", "with  spaces", 29.97, 0), frames)
    stream = read_fap(out)
    back = list(stream)
    assert stream.header == FapHeader("2.1", "with spaces", 29.97, 2)
    assert back[0] == frames[0]
    assert back[1].number == 4 and np.array_equal(back[1].values, frames[1].values)
    assert back[1].viseme is not None  # a single token 7 is read back as viseme 7
    assert back[1].expression is None and any("2500" in w for w in stream.warnings)


def test_write_is_atomic_and_rejects_non_finite_values(tmp_path):
    out = tmp_path / "x.fap"
    out.write_text("previous content\n")
    mask = np.zeros(68, dtype=bool)
    mask[2] = True
    bad = FapFrame(0, mask, np.where(mask, np.nan, 0.0))
    with pytest.raises(ValueError, match="non-finite"):
        write_fap(out, FapHeader("2.1", "x", 25.0, 1), [bad])
    assert out.read_text() == "previous content\n"
    assert [p.name for p in tmp_path.iterdir()] == ["x.fap"]
