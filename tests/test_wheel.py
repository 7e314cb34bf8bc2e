"""fae as a user gets it from a wheel: the shipped head comes inside the package.

The wheel is built from a copy of the sources and installed into a fresh virtual
environment that has no copy of fae but borrows the running environment's dependencies
(a .pth file names its site-packages), so nothing is downloaded but the build backend.
`fae play` and `fae verify-faps` then run from a folder outside the repository.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def run(command: list, cwd: Path, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    done = subprocess.run([str(c) for c in command], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)
    assert done.returncode == 0, f"{command}: exit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.fixture
def installed(tmp_path_factory) -> tuple[Path, dict]:
    """(bin folder of a fresh venv with the wheel installed, environment to run it in)."""
    root = tmp_path_factory.mktemp("wheel")
    source = root / "source"  # a copy, so the build leaves nothing in the checkout
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    shutil.copytree(REPO / "fae", source / "fae", ignore=shutil.ignore_patterns("__pycache__"))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "FAE_TEMPLATES")}
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", root / "dist", source], root, env)
    wheels = list((root / "dist").glob("fae-*.whl"))
    assert len(wheels) == 1, wheels
    names = zipfile.ZipFile(wheels[0]).namelist()
    assert "fae/data/generic_head.glb" in names
    assert "fae/net/view_page/index.html" in names  # the live view's page

    target = root / "venv"
    venv.create(target, with_pip=False)
    python = target / "bin" / "python"
    site = Path(run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], root, env)
                .stdout.strip())
    borrowed = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "borrowed_dependencies.pth").write_text("".join(f"{p}\n" for p in sorted(borrowed)))
    run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", "--no-index", wheels[0]],
        root, env)
    where = run([python, "-c", "import fae; print(fae.__file__)"], root, env).stdout.strip()
    assert Path(where).is_relative_to(target), where  # the wheel's fae, not the checkout's
    return target / "bin", env


def test_installed_wheel_plays_a_stream_and_verifies_faps_on_the_shipped_head(installed, tmp_path):
    bin_dir, env = installed
    lines = (REPO / "fap_streams" / "expressions.fap").read_text().splitlines()
    header = lines[0].split()
    header[-1] = "12"  # the first 12 frames
    stream = tmp_path / "short.fap"
    stream.write_text("\n".join([" ".join(header), *lines[1:25]]) + "\n")
    done = run([bin_dir / "fae", "play", stream, "-o", "short.mp4", "--size", "160x120"], tmp_path, env)
    assert (tmp_path / "short.mp4").stat().st_size > 1000
    assert "12 frames" in done.stderr

    done = run([bin_dir / "fae", "verify-faps", "--faps", "3,19", "--json"], tmp_path, env)
    report = json.loads(done.stdout)
    assert Path(report["head"]).name == "generic_head.glb" and "site-packages" in report["head"]
    assert [r["fap"] for r in report["faps"]] == [3, 19] and report["passed_fraction"] == 1.0
