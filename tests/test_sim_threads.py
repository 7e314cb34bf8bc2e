"""Faces of one head stepped in several threads at once, from their first frame (as the
server's faces are): no crash, and each face's result is the one it gets alone."""

import subprocess
import sys
from pathlib import Path

import pytest

from fae.data import shipped_head_path

ROOT = Path(__file__).resolve().parents[1]

# Runs in a fresh interpreter: the hazard is in the first calls of each kernel in a process,
# and a crash must fail this test rather than end the test run.
SCRIPT = r"""
import sys, threading
import numpy as np
from fae.io.facemodel_gltf import read_facemodel
from fae.io.fap import read_fap
from fae.io.frames import dense_frames
from fae.animate.player import Player, playable_head

base = Player(playable_head(read_facemodel(sys.argv[1])))
frames = list(dense_frames(read_fap(sys.argv[2])))[40:52]
faces = [Player(base.head) for _ in range(4)]
start = threading.Barrier(len(faces))
out = [None] * len(faces)

def play(k):
    start.wait()  # every face's first step at once
    out[k] = np.array([faces[k].step(f, dt=0.04) for f in frames])

threads = [threading.Thread(target=play, args=(k,)) for k in range(len(faces))]
for t in threads:
    t.start()
for t in threads:
    t.join()
alone = Player(base.head)
expected = np.array([alone.step(f, dt=0.04) for f in frames])
moved = float(np.abs(expected[-1] - expected[0]).max())
worst = max(float(np.abs(o - expected).max()) for o in out)
print(f"moved {moved:.6f} worst {worst:.3g}")
sys.exit(0 if moved > 1e-4 and worst < 1e-6 else 1)
"""


@pytest.mark.slow
def test_faces_step_in_threads_from_their_first_frame():
    """Four faces' first steps at once crashed the interpreter (Warp's kernels
    entered for the first time by several threads) in every run before the fix."""
    head = shipped_head_path()
    stream = ROOT / "fap_streams" / "expressions.fap"
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(head), str(stream)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"exit {done.returncode}: {done.stdout[-500:]} {done.stderr[-2000:]}"
    assert "worst" in done.stdout
