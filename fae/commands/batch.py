"""`fae batch JOBS -o OUT_DIR`: render many videos on a Dask cluster (embedded by default).

JOBS is a .csv or .json job list (stream, head, view, size, fps, output) or a glob of .fap
files played on each --head. Outputs already rendered from the same inputs are kept; the
manifest OUT_DIR/manifest.json lists every job. Exit status 0 when every job has its
video, 1 when some failed (the manifest and stderr say why), 2 for bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fae.commands.common import fail, os_error_text, parse_size, timing_problem


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "batch", help="render many .fap streams to videos on a Dask cluster (embedded unless --scheduler)",
        description="Render every job of JOBS, like `fae play` each, on Dask workers: an embedded cluster of "
        "one worker process per two cores, or the cluster of --scheduler. JOBS is a .csv or .json job list "
        "(columns/keys stream, head, view, size, fps, output; stream required) or a glob of .fap files, "
        "each played on every --head. Outputs whose inputs have not changed since an earlier run are kept.")
    parser.add_argument("jobs", metavar="JOBS", help="jobs.csv, jobs.json, or a quoted glob such as 'corpus/*.fap'")
    parser.add_argument("-o", "--output-dir", required=True, metavar="OUT_DIR",
                        help="folder for the videos and manifest.json (created when missing)")
    parser.add_argument("--head", action="append", default=[], metavar="HEAD.glb",
                        help="with a glob: play every stream on this head (repeat for several); with a job "
                        "file: the head of rows that name none (default: the shipped generic head)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: an embedded "
                        "cluster on this machine)")
    parser.add_argument("--workers", type=int, metavar="N",
                        help="worker processes of the embedded cluster (default: one per two cores; "
                        "one job's simulation, rendering and encoding keep about two busy)")
    parser.add_argument("--retries", type=int, default=2, metavar="K",
                        help="tries after the first for a job that fails (default 2)")
    parser.add_argument("--size", type=parse_size, default=parse_size("640x480"), metavar="WxH",
                        help="image size of jobs that give none (default 640x480)")
    parser.add_argument("--view", default="front", help="camera preset of jobs that give none (default front)")
    parser.add_argument("--fps", type=float, default=None, help="frame rate of jobs that give none "
                        "(default: each stream's)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import importlib.util

    from fae.batch.jobs import JobDefaults, JobFileError, load_jobs
    from fae.render.framing import VIEWS

    if importlib.util.find_spec("distributed") is None:
        return fail("batch", "Dask distributed is not installed here: pip install 'fae[batch]' "
                    "(or 'dask[distributed]')", status=1)
    if args.workers is not None and args.scheduler:
        return fail("batch", "--workers sizes the embedded cluster; with --scheduler, start as many "
                    "`dask worker` processes as wanted")
    if args.workers is not None and not 1 <= args.workers <= 1024:
        return fail("batch", f"--workers {args.workers}: expected 1..1024 worker processes")
    if not 0 <= args.retries <= 100:
        return fail("batch", f"--retries {args.retries}: expected 0..100")
    if args.view not in VIEWS:
        return fail("batch", f"--view {args.view!r}: expected one of {', '.join(VIEWS)}")
    width, height = args.size
    if width % 2 or height % 2:
        return fail("batch", f"--size {width}x{height}: H.264 video needs an even width and height")
    problem = timing_problem(args.fps)
    if problem:
        return fail("batch", problem)
    if args.scheduler and "://" not in args.scheduler:
        return fail("batch", f"--scheduler {args.scheduler!r}: expected an address such as tcp://HOST:8786")
    out_dir = Path(args.output_dir)
    if out_dir.exists() and not out_dir.is_dir():
        return fail("batch", f"{out_dir}: is a file, expected the output folder")
    try:
        jobs = load_jobs(args.jobs, heads=args.head, defaults=JobDefaults(view=args.view, size=args.size, fps=args.fps))
    except JobFileError as exc:
        return fail("batch", str(exc))
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return fail("batch", f"{out_dir}: cannot create the output folder ({exc.strerror or exc})")

    from fae.batch.run import ClusterError, run_batch

    try:
        result = run_batch(jobs, out_dir, scheduler=args.scheduler, workers=args.workers, retries=args.retries,
                           source=args.jobs)
    except ClusterError as exc:
        return fail("batch", str(exc))
    except OSError as exc:  # the output folder refused the manifest
        return fail("batch", os_error_text(exc))
    counts = result.counts
    print(f"{result.manifest}: {counts['done']} rendered, {counts['skipped']} kept from an earlier run, "
          f"{counts['failed']} failed, in {result.seconds:.1f} s ({result.scheduler})", file=sys.stderr)
    for entry in result.failed:
        print(f"fae batch: {entry['output']} ({entry['origin']}): {entry['error']}", file=sys.stderr)
    return 1 if result.failed or counts["pending"] else 0
