"""Wall time of `fae` commands as a user runs them: one process each, start to exit.

Each command runs --repeat times two ways, alternated so that a drift of the machine
touches both alike: as the `fae` command does (fae.cli.run: main, then the exit handlers
and an exit without Python's teardown) and, as the baseline, main followed by the usual
interpreter teardown (freeing Warp's modules, MediaPipe's graph, OSMesa's context).
Prints the median seconds of each and their ratio, and the median seconds from each
command's last line of output to its exit (the teardown's share alone, which a long
command's drift does not blur). Commands: `fae inspect` of a shipped stream, `fae render`
of the shipped head, `fae play` of the shipped visemes stream (48 frames, 640x480 mp4),
and `fae adapt` of the bust the tests make
(fae.adapt.synthetic.bust_scan, seed 3; with its FAP calibration) and, with --real, of
the scanned busts in shared/data/heads/busts when that folder is there.

    .venv/bin/python tools/bench_cli.py [--repeat 3] [--real]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REAL_BUSTS = ("marble_bust", "man_with_wreath", "demosthenes")
# the same main() with the interpreter's usual teardown after it
TEARDOWN = "import sys; from fae.cli import main; sys.exit(main(sys.argv[1:]))"


def wall(argv: list[str]) -> tuple[float, float]:
    """(seconds from start to exit, seconds from the command's last line of output, on
    stdout or stderr, to its exit; nan if it printed nothing): the second is the teardown's
    own share, which a long command's drift (a bust's adapt varies by 1-2 s between runs
    here) does not blur. The command's output is unbuffered, so that each line arrives when
    printed (piped, stdout would otherwise come at the exit's flush, after the exit handlers)."""
    t = time.perf_counter()
    last, said = float("nan"), ""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          errors="replace", env=env) as run:
        for line in run.stdout:
            last, said = time.perf_counter(), (said + line)[-400:]
    end = time.perf_counter()
    if run.returncode != 0:
        raise SystemExit(f"bench_cli: {' '.join(argv)} exited {run.returncode}: {said.strip()}")
    return end - t, end - last


def synthetic_bust(folder: Path) -> Path:
    import trimesh

    from fae.adapt.synthetic import template_bust
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel

    bust = template_bust(read_facemodel(shipped_head_path()))
    path = folder / "bust.obj"
    trimesh.Trimesh(bust.vertices, bust.faces, process=False).export(path)
    return path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3, help="runs of each command each way; the median counts")
    ap.add_argument("--real", action="store_true", help="also `fae adapt` the scanned busts of shared/data")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        commands = [("inspect a stream", ["inspect", "fap_streams/expressions.fap"]),
                    ("render the shipped head", ["render", "-o", str(folder / "r.png")]),
                    ("play visemes.fap to mp4", ["play", "fap_streams/visemes.fap", "-o", str(folder / "v.mp4")]),
                    ("adapt the synthetic bust", ["adapt", str(synthetic_bust(folder)), "-o", str(folder / "h.glb")])]
        busts = ROOT.parent / "shared" / "data" / "heads" / "busts"
        if args.real and busts.is_dir():
            commands += [(f"adapt {name}", ["adapt", str(busts / name / f"{name}.obj"), "-o", str(folder / "h.glb")])
                         for name in REAL_BUSTS]
        elif args.real:
            print(f"note: {busts} not found; the scanned busts are left out")
        print(f"{'command':28s} {'fae (s)':>8s} {'with teardown (s)':>18s} {'ratio':>6s}   "
              f"{'last output to exit: fae / with teardown (s)':>44s}")
        for name, argv in commands:
            quick, full = [], []
            for _ in range(args.repeat):
                quick.append(wall([sys.executable, "-m", "fae", *argv]))
                full.append(wall([sys.executable, "-c", TEARDOWN, *argv]))
            q, f = (statistics.median(t for t, _ in runs) for runs in (quick, full))
            qe, fe = (statistics.median(e for _, e in runs) for runs in (quick, full))
            print(f"{name:28s} {q:8.2f} {f:18.2f} {f / q:6.2f}x   {qe:24.2f} / {fe:.2f}")


if __name__ == "__main__":
    main()
