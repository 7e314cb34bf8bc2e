"""`fae adapt SCAN [--landmarks FILE] [--template FILE] [--method M] -o HEAD.glb [--report R.json] [--plot R.png]`

Fits the template head to a scan and writes the personalized FaceModel. Without
--landmarks the feature points are found on the scan (fae.adapt.auto_landmarks). Exit 0 on success,
2 on bad input (the reason, naming the file and field, on stderr).
"""

from __future__ import annotations

import json
import os
import sys
import time

from fae.adapt.multilevel import METHODS

DEFAULT_TEMPLATE = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "templates", "generic_head.glb")


def register(subparsers) -> None:
    p = subparsers.add_parser("adapt", help="fit the template head to a scan (personalization)",
                              description="Fit the anatomical template to a head scan (any mesh trimesh "
                              "reads, any unit and orientation) from MPEG-4 feature points, carry skull, "
                              "jaw, muscles, eyes, teeth and tongue over, and write the personalized head.")
    p.add_argument("scan", metavar="SCAN", help="head mesh (OBJ, PLY, STL, OFF, GLB/glTF)")
    p.add_argument("--landmarks", metavar="FILE", help="feature points: JSON {\"9.3\": [x, y, z] or vertex "
                   "index}, menpo .ljson or CSV (68 iBUG points or name,x,y,z rows)")
    p.add_argument("--feature-search", choices=("fit", "ga"), default="fit",
                   help="without --landmarks: refine the found feature points by the template fit (default) or "
                   "by paper 003's genetic algorithm")
    p.add_argument("--template", metavar="FILE", default=DEFAULT_TEMPLATE, help="template FaceModel .glb")
    p.add_argument("--method", choices=METHODS, default="multilevel", help="fitting method (default: multilevel)")
    p.add_argument("--levels", type=int, default=1, help="refinement levels after the first (multilevel)")
    p.add_argument("-o", "--output", required=True, metavar="HEAD.glb", help="personalized FaceModel to write")
    p.add_argument("--report", metavar="R.json", help="write the per-level error report as JSON")
    p.add_argument("--plot", metavar="R.png", help="plot the errors per level (PNG)")
    p.add_argument("--no-calibrate", action="store_true",
                   help="skip deriving the runtime's FAP mapping for the new head (the player then "
                   "derives it each time it loads the head, which takes minutes)")
    p.set_defaults(func=run)


def write_plot(report: dict, path: str) -> None:
    """Errors per level (paper 000 tables 1-2 as a chart), written atomically to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fae.io.atomic import atomic_path

    lv = report["levels"]
    x = [r["level"] for r in lv]
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in ("distance_error", "marker_error", "combined_error"):
        ax.plot(x, [r[key] * 1000 for r in lv], marker="o", label=key.replace("_", " "))
    ax.set_xlabel("level")
    ax.set_ylabel("error (mm)")
    ax.set_title(f"fae adapt ({report.get('method', '')})")
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def run(args) -> int:
    from tqdm import tqdm

    from fae.adapt.transfer import adapt_facemodel
    from fae.io.atomic import atomic_open
    from fae.io.facemodel_gltf import read_facemodel, write_facemodel
    from fae.io.scan import LandmarkError, read_landmarks, read_scan

    try:
        V, F = read_scan(args.scan)
        landmarks = read_landmarks(args.landmarks, V) if args.landmarks else None
        if not os.path.isfile(args.template):
            print(f"fae adapt: template {args.template} not found (build it with `fae template`)", file=sys.stderr)
            return 2
        template = read_facemodel(args.template)
    except (OSError, ValueError, LandmarkError) as exc:
        print(f"fae adapt: {exc}", file=sys.stderr)
        return 2
    bar = tqdm(total=args.levels + 6, desc="adapt", unit="level", file=sys.stderr)

    def progress(msg: str) -> None:
        bar.update(1)
        bar.set_postfix_str(msg)

    try:
        auto = None
        if landmarks is None:
            from fae.adapt.auto_landmarks import auto_landmarks

            landmarks, auto = auto_landmarks(template, V, F, method=args.feature_search)
            print(f"fae adapt: {len(landmarks)} feature points found automatically ({args.feature_search}; "
                  f"nose tip detected: {'9.3' in auto['detected']})", file=sys.stderr)
        model, report = adapt_facemodel(template, V, F, landmarks, method=args.method, levels=args.levels,
                                        progress=progress)
    except ValueError as exc:
        bar.close()
        print(f"fae adapt: {args.scan}: {exc}", file=sys.stderr)
        return 2
    bar.close()
    if auto is not None:
        report["automatic_feature_points"] = auto
    if not args.no_calibrate:
        # Setup work belongs here, once per head: the player then loads the head at once.
        from fae.animate.calibrate import calibrate

        print("fae adapt: deriving the FAP mapping of the new head (once per head)", file=sys.stderr)
        started = time.perf_counter()
        model = calibrate(model)
        report["calibration_seconds"] = time.perf_counter() - started
    write_facemodel(model, args.output)
    if args.report:
        with atomic_open(args.report, "w") as fh:
            json.dump(report, fh, indent=1)
    if args.plot:
        write_plot(report, args.plot)
    f = report["final"]
    for name, why in report["ignored_landmarks"].items():
        print(f"fae adapt: ignored feature point {name}: {why}", file=sys.stderr)
    print(f"{args.output}: scan->model RMS {f['scan_to_model_rms'] * 1000:.3f} mm, model->scan RMS "
          f"{f['model_to_scan_rms'] * 1000:.3f} mm, marker error {f['marker_error'] * 1000:.3f} mm, "
          f"{f['seconds']:.1f} s")
    return 0
