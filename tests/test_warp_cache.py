"""Caches where their own folders cannot be made (a read-only home): Warp's kernel cache
moves to a folder of the system's temporary directory, said in one line (every command that
runs a kernel stopped with a traceback), and matplotlib's (the error plot) quietly."""

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


def test_the_error_plot_under_a_home_that_cannot_be_written_is_drawn_without_a_word(tmp_path):
    """`fae adapt --plot` with a read-only home: matplotlib said in two lines that its config
    folder could not be made (and rebuilt its font cache each run); its cache now goes to a
    private folder of the temporary directory, quietly."""
    home = tmp_path / "home_is_a_file"
    home.write_text("not a folder")
    env = {k: v for k, v in os.environ.items() if k not in ("MPLCONFIGDIR", "XDG_CONFIG_HOME", "XDG_CACHE_HOME")}
    env.update(HOME=str(home), TMPDIR=str(tmp_path))
    out = tmp_path / "levels.png"
    code = ("from fae.commands.adapt import write_plot\n"
            "write_plot({'method': 'rbf', 'levels': [{'level': i, 'distance_error': 0.001 / (i + 1), "
            f"'marker_error': 0.0005, 'combined_error': 0.001}} for i in range(3)]}}, {str(out)!r})\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "matplotlib" not in done.stderr.lower(), done.stderr
    folder = tmp_path / f"fae-matplotlib-{os.getuid()}"
    assert folder.is_dir() and folder.stat().st_mode & 0o077 == 0
