"""What native libraries print on stderr: filtered, fae's own messages left readable."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from fae.native_stderr import native_stderr_filtered

ROOT = Path(__file__).resolve().parents[1]


def test_native_lines_are_kept_or_left_out_as_asked(capfd):
    with native_stderr_filtered(keep=lambda line: "driver" not in line):
        os.write(2, b"first line kept\nno NVIDIA CUDA driver here\nlast line kept\n")
    assert capfd.readouterr().err == "first line kept\nlast line kept\n"
    with native_stderr_filtered():
        os.write(2, b"a C++ core's start-up log\n")
    print("fae's own message", file=sys.stderr)
    assert capfd.readouterr().err == "fae's own message\n"


def test_a_command_says_nothing_of_a_missing_gpu_driver(tmp_path):
    # fae runs on the CPU by default; Warp's native core announces a missing NVIDIA driver
    # on every machine without one
    done = subprocess.run([sys.executable, "-m", "fae", "verify-faps", "--faps", "19", "--json"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "CUDA" not in done.stderr and '"passed_fraction"' in done.stdout
