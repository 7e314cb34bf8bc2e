"""Warp's kernel cache where its own folder cannot be made (a read-only home): fae goes on
with a folder of the system's temporary directory and says so, instead of stopping every
command that runs a kernel with a traceback."""

from __future__ import annotations

import os
import subprocess
import sys


def test_an_unmakeable_kernel_cache_falls_back_to_the_temporary_directory(tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the cache's parent folder would be")
    env = {**os.environ, "WARP_CACHE_PATH": str(blocker / "cache"), "TMPDIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", "from fae.warp_setup import wp; print(wp.config.kernel_cache_dir)"],
                          capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    assert "Warp's kernel cache cannot be made" in done.stderr and "WARP_CACHE_PATH" in done.stderr
    cache = done.stdout.strip().splitlines()[-1]
    assert cache.startswith(str(tmp_path / "fae-warp-cache-")) and os.path.isdir(cache)
    # compiled kernels are loaded from it: no one else may write there
    assert os.stat(os.path.dirname(cache)).st_mode & 0o077 == 0
