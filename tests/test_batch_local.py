"""`fae batch` on its embedded cluster: a glob of streams on two heads, one worker process.
Each head is set up once on the worker, not once per job, and a video is the one `fae play`
writes for the same stream, head, view and size."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest

from batch_support import short_stream, tinted_head, video_frames

pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parent.parent


def decoded(path: Path) -> list[np.ndarray]:
    reader = imageio_ffmpeg.read_frames(str(path))
    next(reader)
    return [np.frombuffer(b, dtype=np.uint8) for b in reader]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_embedded_cluster_sets_each_head_up_once_and_renders_like_play(tmp_path):
    from fae.data import shipped_head_path

    (tmp_path / "corpus").mkdir()
    counts = {"one": 6, "two": 9, "three": 12}
    for name, n in counts.items():
        short_stream(tmp_path / "corpus" / f"{name}.fap", n)
    tinted_head(tmp_path / "tinted.glb")
    generic = tmp_path / "generic.glb"
    generic.write_bytes(shipped_head_path().read_bytes())
    command = [sys.executable, "-m", "fae", "batch", "corpus/*.fap", "--head", "generic.glb", "--head", "tinted.glb",
               "-o", "out", "--workers", "1", "--size", "160x120", "--view", "three-quarter"]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stderr
    assert "6 rendered, 0 kept from an earlier run, 0 failed" in result.stderr
    entries = json.loads((tmp_path / "out" / "manifest.json").read_text())["jobs"]
    assert len(entries) == 6 and all(e["status"] == "done" for e in entries)
    for entry in entries:
        stream = Path(entry["inputs"]["stream"]["path"]).stem
        assert video_frames(tmp_path / "out" / entry["output"]) == counts[stream] == entry["frames"]
    assert len({e["worker"] for e in entries}) == 1
    assert sum(not e["head_reused"] for e in entries) == 2  # one set-up per head on the one worker

    play = subprocess.run([sys.executable, "-m", "fae", "play", "corpus/two.fap", "--head", "tinted.glb",
                           "-o", "play.mp4", "--size", "160x120", "--view", "three-quarter"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert play.returncode == 0, play.stderr
    batch_frames, play_frames = decoded(tmp_path / "out" / "two-tinted.mp4"), decoded(tmp_path / "play.mp4")
    assert len(batch_frames) == len(play_frames) == 9
    assert all(np.array_equal(a, b) for a, b in zip(batch_frames, play_frames))


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_a_head_that_is_not_a_facemodel_fails_its_job_with_the_reason(tmp_path):
    short_stream(tmp_path / "talk.fap", 4)
    (tmp_path / "broken.glb").write_bytes(b"glTF but not really")
    (tmp_path / "jobs.json").write_text(json.dumps([{"stream": "talk.fap", "head": "broken.glb", "size": "64x48"}]))
    result = subprocess.run([sys.executable, "-m", "fae", "batch", "jobs.json", "-o", "out", "--workers", "1",
                             "--retries", "1"], cwd=tmp_path, capture_output=True, text=True, timeout=110)
    assert result.returncode == 1, result.stderr
    (entry,) = json.loads((tmp_path / "out" / "manifest.json").read_text())["jobs"]
    assert entry["status"] == "failed" and entry["attempts"] == 2
    assert "broken.glb" in entry["error"] and "Traceback" not in result.stderr
    assert "talk.mp4 (jobs.json job 1): " in result.stderr
    assert not (tmp_path / "out" / "talk.mp4").exists()
