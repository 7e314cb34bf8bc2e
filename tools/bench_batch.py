"""Videos/s of `fae batch` with 1 and with 2 workers against a loop of `fae play`.

    .venv/bin/python tools/bench_batch.py [--jobs 8] [--frames 50] [--size 320x240]
                                          [--stream fap_streams/expressions.fap]

N jobs, each a stream of --frames frames cut from --stream (each job a different start,
so no two videos are alike), on the shipped head, rendered three ways in one run:
  play loop    `fae play` once per job, one after the other, each a fresh process (the
               shell loop `fae batch` replaces: the head is set up for every file)
  batch 1      `fae batch --workers 1`: one worker process, the head set up once
  batch 2      `fae batch --workers 2`: two worker processes, the head set up once on each
Each batch run starts with an empty output folder, and its time includes starting the
embedded cluster. Prints videos/s for each and the ratios against the play loop and
batch 2 against batch 1.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def cut_streams(source: Path, folder: Path, jobs: int, frames: int) -> list[Path]:
    """`jobs` streams of `frames` frames each, from different starts in `source`."""
    lines = source.read_text().splitlines()
    header = lines[0].split()
    body = lines[1:]
    total = len(body) // 2
    if total < frames:
        raise SystemExit(f"{source}: {total} frames, fewer than --frames {frames}")
    header[-1] = str(frames)
    paths = []
    for i in range(jobs):
        start = (i * max(1, (total - frames) // max(1, jobs - 1))) if jobs > 1 else 0
        start = min(start, total - frames)
        chunk = body[2 * start:2 * (start + frames)]
        path = folder / f"job{i:02d}.fap"
        path.write_text(" ".join(header) + "\n" + "\n".join(chunk) + "\n")
        paths.append(path)
    return paths


def run(command: list[str], env: dict) -> float:
    t = time.perf_counter()
    result = subprocess.run(command, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stderr[-2000:]}")
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=8)
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--stream", type=Path, default=REPO / "fap_streams" / "expressions.fap")
    args = parser.parse_args()

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("PYOPENGL_PLATFORM", "osmesa")
    fae = [sys.executable, "-m", "fae"]
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
        folder = Path(tmp)
        (folder / "streams").mkdir()
        streams = cut_streams(args.stream, folder / "streams", args.jobs, args.frames)
        print(f"{args.jobs} jobs of {args.frames} frames at {args.size}, shipped head, "
              f"{len(os.sched_getaffinity(0))} usable cores")

        (folder / "play").mkdir()
        loop_s = sum(run([*fae, "play", str(s), "-o", str(folder / "play" / f"{s.stem}.mp4"), "--size", args.size],
                         env) for s in streams)
        results = {"play loop": loop_s}
        details = {"play loop": f"{loop_s / args.jobs:.2f} s a job, each a new process"}
        for workers in (1, 2):
            out = folder / f"batch{workers}"
            seconds = run([*fae, "batch", str(folder / "streams" / "*.fap"), "-o", str(out), "--size", args.size,
                           "--workers", str(workers)], env)
            manifest = json.loads((out / "manifest.json").read_text())
            assert manifest["summary"]["done"] == args.jobs, manifest["summary"]
            results[f"batch {workers}"] = seconds
            first = [e["seconds"] for e in manifest["jobs"] if not e["head_reused"]]
            later = sorted(e["seconds"] for e in manifest["jobs"] if e["head_reused"])
            details[f"batch {workers}"] = (f"first job on each worker (head set-up included) "
                                           f"{', '.join(f'{s:.1f}' for s in first)} s, later jobs median "
                                           f"{later[len(later) // 2]:.2f} s" if later else "")

    rate = {name: args.jobs / seconds for name, seconds in results.items()}
    for name, seconds in results.items():
        print(f"{name:10s} {seconds:7.1f} s  {rate[name]:6.3f} videos/s  "
              f"{rate[name] / rate['play loop']:5.2f}x the play loop   ({details[name]})")
    print(f"batch 2 / batch 1: {rate['batch 2'] / rate['batch 1']:.2f}x")


if __name__ == "__main__":
    main()
