"""`fae adapt SCAN [--landmarks FILE] [--template FILE] [--method M] -o HEAD.glb [--report R.json] [--plot R.png]`

Fits the template head to a scan and writes the personalized FaceModel.

The default method, "surface": the head is found in the scan (any unit and orientation;
plinth, shoulders and chest left out: fae.adapt.head_pose), corresponding points are
found by a face-landmark model looking at the template and at the scan from the same
camera (fae.render.landmarks; feature points given with --landmarks join them), the skin
is fitted to the head part without folds (fae.adapt.nonrigid) and the anatomy carried
over (fae.adapt.transfer); fae.adapt.workflow.adapt_scan runs these steps, this command
reads the inputs, calibrates, draws and writes. The paper methods ("multilevel", "rbf", "wendland",
"multiquadric") fit the whole scan from feature points, as in papers 000-002.

Exit 0 on success; 2 on bad input, or when fae cannot find the head or its face, or the
result is not to be trusted (folded skin, a face far from the scan): the reason goes to
stderr and no head is written (the --report, when asked for, says what was measured).
--force writes such a head anyway. --plot, --levels and --feature-search belong to the
paper methods.
"""

from __future__ import annotations

import os
import sys
import time

from fae.adapt import PAPER_METHODS
from fae.data import shipped_head_path

ADAPT_METHODS = ("surface",) + PAPER_METHODS
DEFAULT_TEMPLATE = str(shipped_head_path())
MAX_LEVELS = 4  # each level doubles the pairs: the menpo3d mask's sixth of 50 held 195k of them and 11 GB


def register(subparsers) -> None:
    p = subparsers.add_parser("adapt", help="fit the template head to a scan (personalization)",
                              description="Fit the anatomical template to a head scan (any mesh trimesh "
                              "reads, any unit and orientation, a bust on its plinth; feature points are "
                              "found when none are given), carry skull, jaw, muscles, eyes, teeth and tongue "
                              "over, and write the personalized head.")
    p.add_argument("scan", metavar="SCAN", nargs="?", help="head mesh (OBJ, PLY, STL, OFF, GLB/glTF)")
    p.add_argument("--photo", metavar="FACE.jpg", help="instead of a scan: one frontal photo of a face (JPEG, PNG); "
                   "the head is shaped from the face's points and coloured from the photo (paper 002)")
    p.add_argument("--landmarks", metavar="FILE", help="feature points: JSON {\"9.3\": [x, y, z] or vertex "
                   "index}, menpo .ljson or CSV (68 iBUG points or name,x,y,z rows)")
    p.add_argument("--feature-search", choices=("fit", "ga"), default=None,
                   help="paper methods without --landmarks: refine the feature points found by ICP with the "
                   "template fit (default) or by paper 003's genetic algorithm")
    p.add_argument("--template", metavar="FILE", default=DEFAULT_TEMPLATE, help="template FaceModel .glb")
    p.add_argument("--method", choices=ADAPT_METHODS, default="surface",
                   help="fitting method (default: surface; the others are the papers' feature-point fits)")
    p.add_argument("--levels", type=int, default=None, help=f"refinement levels after the first (multilevel; "
                   f"0-{MAX_LEVELS}, default 1)")
    p.add_argument("-o", "--output", required=True, metavar="HEAD.glb", help="personalized FaceModel to write")
    p.add_argument("--report", metavar="R.json", help="write the report (errors, coverage, folds, the head "
                   "part used, confidence, per stage or level) as JSON")
    p.add_argument("--plot", metavar="R.png", help="plot the errors per level (PNG; paper methods)")
    p.add_argument("--compare", metavar="C.png", help="picture of the scan beside the adapted head and both "
                   "overlaid, front and profile (PNG)")
    p.add_argument("--force", action="store_true", help="write the head even when the fit is not to be trusted")
    p.add_argument("--no-calibrate", action="store_true",
                   help="skip deriving the runtime's FAP mapping for the new head (the player then "
                   "derives it each time it loads the head, which takes minutes)")
    p.set_defaults(func=run)


def write_plot(report: dict, path: str) -> None:
    """Errors per level (paper 000 tables 1-2 as a chart), written atomically to `path`."""
    import os

    from fae.private_folder import private_temporary_folder, writable_folder

    folders = [os.path.join(os.environ.get(variable) or os.path.expanduser(default), "matplotlib")
               for variable, default in (("XDG_CONFIG_HOME", "~/.config"), ("XDG_CACHE_HOME", "~/.cache"))]
    if "MPLCONFIGDIR" not in os.environ and not all(writable_folder(folder) for folder in folders):
        # a home that cannot be written: matplotlib said so in two lines and rebuilt its font cache
        # each run (MPLCONFIGDIR holds both its config and its cache)
        os.environ["MPLCONFIGDIR"] = private_temporary_folder("fae-matplotlib")
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
    # the seconds reported are the user's wait: reading the scan and the template and the
    # imports they need (about a second) count too, not the fit and calibration alone
    started = time.perf_counter()
    from fae.commands.adapt_checks import landmark_problem, scan_outward, scan_problem
    from fae.commands.common import overwritten_input
    from fae.io.scan import LandmarkError, indexed_vertices, read_landmarks, read_scan

    if (args.scan is None) == (args.photo is None):
        print("fae adapt: give either a scan (SCAN) or --photo FACE.jpg", file=sys.stderr)
        return 2
    if args.photo is not None:
        return _run_photo(args, started)
    if args.method != "surface" and args.compare:
        print("fae adapt: --compare needs --method surface", file=sys.stderr)
        return 2
    paper_only = [flag for flag, value in (("--plot", args.plot), ("--levels", args.levels),
                                           ("--feature-search", args.feature_search)) if value is not None]
    if args.method == "surface" and paper_only:  # they were ignored without a word (no plot written)
        print(f"fae adapt: {', '.join(paper_only)} belong{'s' if len(paper_only) == 1 else ''} to the paper methods "
              f"(--method {' | '.join(PAPER_METHODS)}); the default surface fit reports per stage in --report",
              file=sys.stderr)
        return 2
    if args.feature_search is not None and args.landmarks:
        print("fae adapt: --feature-search finds feature points where none are given; --landmarks gives them",
              file=sys.stderr)
        return 2
    if args.levels is not None and not 0 <= args.levels <= MAX_LEVELS:
        print(f"fae adapt: --levels {args.levels}: expected 0-{MAX_LEVELS} levels after the first", file=sys.stderr)
        return 2
    args.levels = 1 if args.levels is None else args.levels
    args.feature_search = args.feature_search or "fit"
    outputs = {"-o": args.output, "--report": args.report, "--plot": args.plot, "--compare": args.compare}
    try:
        problem = overwritten_input(outputs, {"scan": args.scan, "--landmarks file": args.landmarks,
                                              "--template": args.template}) or _outputs_problem(outputs)
        if problem:
            raise ValueError(problem)
        if args.method == "surface":  # imported while the scan is read and its head found
            from fae.render.landmarks import preload_landmark_model

            preload_landmark_model()
        V, F = read_scan(args.scan)
        problem = scan_problem(V, F, args.scan)
        landmarks = read_landmarks(args.landmarks, lambda: indexed_vertices(args.scan, V)) \
            if args.landmarks and not problem else None
        if landmarks is not None:
            problem = landmark_problem(V, landmarks, args.landmarks, args.scan)
        if problem:
            raise ValueError(problem)
        F, args.turned_outward = scan_outward(V, F, args.scan, _say)
        template = _read_template(args.template, args.force)
    except (OSError, ValueError, LandmarkError) as exc:
        print(f"fae adapt: {exc}", file=sys.stderr)
        return 2
    if args.method == "surface":
        return _run_surface(args, template, V, F, landmarks, started)
    return _run_paper(args, template, V, F, landmarks, started)


def _head_problems(model) -> list[str]:
    """fae.anatomy.checks.facemodel_problems, a check that fails being one more problem."""
    from fae.anatomy.checks import facemodel_problems

    try:
        return facemodel_problems(model)
    except Exception as exc:  # noqa: BLE001 - a head that cannot be checked is not taken as whole
        return [f"it could not be checked ({type(exc).__name__}: {exc})"]


def _read_template(path: str, force: bool = False):
    """The template FaceModel at `path`; raises ValueError naming it when it is missing or a
    folder, or when a template other than the shipped one is not a whole head (found only
    after the fit, it was blamed on the scan); with `force`, says so and goes on."""
    from fae.io.facemodel_gltf import read_facemodel

    if os.path.isdir(path):
        raise ValueError(f"template {path} is a folder, expected a FaceModel .glb")
    if not os.path.isfile(path):
        raise ValueError(f"template {path} not found (build it with `fae template`)")
    template = read_facemodel(path)
    if os.path.realpath(path) != os.path.realpath(DEFAULT_TEMPLATE):
        problems = _head_problems(template)
        if problems:
            why = f"template {path}: not a whole head ({problems[0]}; `fae template check` lists all)"
            if not force:
                raise ValueError(why + "; --force fits it anyway")
            _say(f"warning: {why}")
    return template


OUTPUT_SUFFIXES = {"-o": ".glb", "--report": ".json", "--plot": ".png", "--compare": ".png"}


def _outputs_problem(outputs: dict[str, str | None]) -> str | None:
    """Why one of the outputs asked for (flag -> path) cannot be written, or None: each in
    its folder, with its own suffix (a head written as x.txt, a report as r.png were
    written without a word)."""
    from fae.commands.common import output_problem

    for flag, path in outputs.items():
        problem = path and output_problem(path, OUTPUT_SUFFIXES[flag])
        if problem:
            return f"{flag} {problem}"
    return None


def lids_off_their_eyes(report: dict) -> str | None:
    """A warning when an upper lid of the adapted head lies farther than LID_GAP_WARNED off
    its eyeball (the report's lid_gap_m; fae.adapt.transfer.lid_gaps), else None."""
    from fae.adapt.transfer import LID_GAP_WARNED

    gaps = {eye: g["upper"] for eye, g in (report.get("lid_gap_m") or {}).items()}
    if not gaps or max(gaps.values()) <= LID_GAP_WARNED:
        return None
    shown = ", ".join(f"{eye} {gap * 1000:.1f} mm" for eye, gap in sorted(gaps.items()))
    return (f"the upper lids' margins lie off their eyeballs ({shown}; warned above {LID_GAP_WARNED * 1000:.0f} "
            "mm): the eyes sit deep behind the lids (see them from the side with fae render --view profile)")


def _say(msg: str) -> None:
    print(f"fae adapt: {msg}", file=sys.stderr)


def _run_surface(args, template, V, F, landmarks, started: float) -> int:
    from fae.adapt.workflow import AdaptRefused, adapt_scan

    try:
        model, report, keep = adapt_scan(template, V, F, _face_pairs(template), landmarks, scan_name=args.scan,
                                         landmarks_name=args.landmarks, say=_say, search_with_landmarks=True)
    except AdaptRefused as exc:
        _say(str(exc))
        return 2
    return _finish(args, model, report, V, F, keep, started, template.fap_mapping)


def _face_pairs(template):
    """The face-landmark model's corresponding points on a head part (fae.render.landmarks),
    as fae.adapt.workflow asks for them."""
    from fae.adapt.transfer import visible_skin
    from fae.adapt.workflow import FacePairsUnavailable
    from fae.render.framing import camera_view
    from fae.render.landmarks import LandmarkModelMissing, landmark_pairs

    def find(part_V, part_F):
        try:
            return landmark_pairs(template, part_V, part_F, camera_view(template, "front", aspect=1.0),
                                  seen=visible_skin(template))
        except LandmarkModelMissing as exc:
            raise FacePairsUnavailable(str(exc), fatal=False) from exc
        except (RuntimeError, ImportError, OSError) as exc:  # no OpenGL to draw the faces with
            raise FacePairsUnavailable(f"cannot render the scan to find its face ({exc}); is OSMesa installed "
                                       "(make install)?", fatal=True) from exc

    return find


def _finish(args, model, report, V, F, keep, started, start_mapping=None) -> int:
    from fae.commands.adapt_checks import implausible_fit

    verdict = report["verdict"] = report.get("verdict", []) + implausible_fit(report)
    report["scan_turned_outward"] = bool(getattr(args, "turned_outward", False))
    if _refused(args, args.scan, verdict, report, "; --landmarks may help"):
        return 2
    deep = lids_off_their_eyes(report)
    if deep:
        _say(deep)
    model = _calibrated_if_whole(args, args.scan, model, report, start_mapping)
    if model is None:
        return 2
    picture = None
    if args.compare:  # drawn before anything is written: a failure here leaves nothing behind
        from fae.render.compare import comparison_image

        try:
            picture = comparison_image(model, V, F, keep)
        except (RuntimeError, ImportError, OSError) as exc:
            _say(f"cannot draw {args.compare} ({exc}); is OSMesa installed (make install)?")
            return 2
    report["total_seconds"] = time.perf_counter() - started
    _write_outputs(args, model, report, picture)
    e = report["errors"]
    part = report["head_part"]
    print(f"{args.output}: head part {part['head_vertices']} of {part['scan_vertices']} scan vertices; face skin->scan "
          f"RMS {e['face_to_scan_rms_rel'] * 100:.3f} % of the head diagonal ({e['face_coverage'] * 100:.0f} % "
          f"covered), scan->skin RMS {e['scan_to_skin_rms_rel'] * 100:.3f} % ({e['scan_coverage'] * 100:.0f} % "
          f"covered; without the neck {e['head_to_skin_rms_rel'] * 100:.3f} %), "
          f"{e['scan_to_skin_all_rms_rel'] * 100:.3f} % counting every point; "
          f"{report['folded_triangles']['visible']} folded triangles; {report['total_seconds']:.1f} s")
    if report.get("scan_covers_part_of_head"):
        print(f"{args.output}: the scan covers only part of the head: where it has no surface, the head "
              "keeps the template's shape")
    notice = _size_notice(report)
    if notice:
        print(f"{args.output}: {notice}")
    return 0


SIZE_NOTICE = (0.85, 1.18)  # the head's size over the template's beyond which the unit taken is said


def _size_notice(report: dict) -> str | None:
    """What a user should know of the unit the scan was taken in, or None: a unit that makes
    the head much smaller or larger than the template (a scan in no unit, 7 of them to a
    metre, was read as decimetres: a head 0.70x life size, said nowhere but in --report),
    or none fae knows (the head then has the template's size)."""
    unit = (report.get("head_part") or {}).get("scan_unit", report.get("scan_unit"))
    ratio = report.get("fapu_ratio")
    if unit == "unknown":
        return ("the scan's unit is none fae knows (mm, cm, dm, m, inches): the head has the template's "
                "size; scale the scan to a unit of length for the person's own")
    if isinstance(ratio, (int, float)) and not SIZE_NOTICE[0] <= ratio <= SIZE_NOTICE[1]:
        return (f"the scan's unit taken as {unit}: the head is {ratio:.2f}x the template's size (its FAPU); if "
                "that is not the person's size, scale the scan to millimetres or metres")
    return None


def _refused(args, source: str, verdict: list[str], report: dict, hint: str = "") -> bool:
    """Say each reason the head is not to be trusted; True when nothing is to be written
    (a verdict without --force), after writing the report when asked for."""
    from fae.commands.common import json_text
    from fae.io.atomic import atomic_open

    for why in verdict:
        _say(f"{source}: {why}")
    if not verdict or args.force:
        return False
    _say(f"not writing {args.output}: the head is not to be trusted (--force writes it anyway{hint})")
    if args.report:
        with atomic_open(args.report, "w") as fh:
            fh.write(json_text(report, indent=1))
    return True


def _write_outputs(args, model, report: dict, picture) -> None:
    """The head (-o), the report (--report) and the picture (--compare), each atomically."""
    from fae.commands.common import json_text
    from fae.io.atomic import atomic_open, atomic_path
    from fae.io.facemodel_gltf import write_facemodel

    write_facemodel(model, args.output)
    if args.report:
        with atomic_open(args.report, "w") as fh:
            fh.write(json_text(report, indent=1))
    if picture is not None:
        from fae.render.png import write_png

        with atomic_path(args.compare) as tmp:
            write_png(tmp, picture)


def _calibrated_if_whole(args, source: str, model, report: dict, start_mapping: dict | None = None):
    """The model calibrated (_calibrated), or None when it is not whole (fae template
    check's problems: skin inside a bone, a bone through the skin, the skin cutting
    through itself, ...) and --force was not given: each problem is said, as
    `fae template check` would, and nothing is written. The check runs beside the
    calibration (the busts' calibration took as long with it as without). A check that
    fails to run counts as a problem."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1) as pool:
        check = pool.submit(_head_problems, model)
        calibrated = _calibrated(args, model, report, start_mapping)
        problems = [f"the head is not whole ({p}): `fae template check` would fail it" for p in check.result()]
    if problems:
        report["verdict"] = report.get("verdict", []) + problems
        if _refused(args, source, problems, report):
            return None
    return calibrated


def _calibrated(args, model, report: dict, start_mapping: dict | None = None):
    """The model with its FAP mapping derived (unless --no-calibrate); the seconds go into
    the report. Setup work belongs here, once per head: the player then loads it at once.
    start_mapping: the template's, whose table scales start the calibration (one pass
    instead of three; see fae.animate.calibrate)."""
    if args.no_calibrate:
        return model
    from fae.animate.calibrate import calibrate

    _say("deriving the FAP mapping of the new head (once per head)")
    started = time.perf_counter()
    model = calibrate(model, start=start_mapping)
    report["calibration_seconds"] = time.perf_counter() - started
    return model


def _run_paper(args, template, V, F, landmarks, started: float) -> int:
    from tqdm import tqdm

    from fae.adapt.transfer import adapt_facemodel

    bar = tqdm(total=args.levels + 6, desc="adapt", unit="level", file=sys.stderr)

    def progress(msg: str) -> None:
        bar.update(1)
        bar.set_postfix_str(msg)

    try:
        auto = None
        if landmarks is None:
            from fae.adapt.auto_landmarks import auto_landmarks

            landmarks, auto = auto_landmarks(template, V, F, method=args.feature_search)
            _say(f"{len(landmarks)} feature points found automatically ({args.feature_search}; "
                 f"nose tip detected: {'9.3' in auto['detected']})")
        model, report = adapt_facemodel(template, V, F, landmarks, method=args.method, levels=args.levels,
                                        progress=progress)
    except ValueError as exc:
        bar.close()
        _say(f"{args.scan}: {exc}")
        return 2
    bar.close()
    if auto is not None:
        report["automatic_feature_points"] = auto
    from fae.commands.adapt_checks import implausible_fit

    verdict = report["verdict"] = implausible_fit(report)
    if _refused(args, args.scan, verdict, report):
        return 2
    model = _calibrated_if_whole(args, args.scan, model, report, template.fap_mapping)
    if model is None:
        return 2
    report["total_seconds"] = time.perf_counter() - started
    _write_outputs(args, model, report, None)
    if args.plot:
        write_plot(report, args.plot)
    f = report["final"]
    for name, why in report["ignored_landmarks"].items():
        _say(f"ignored feature point {name}: {why}")
    print(f"{args.output}: scan->model RMS {f['scan_to_model_rms'] * 1000:.3f} mm, model->scan RMS "
          f"{f['model_to_scan_rms'] * 1000:.3f} mm, marker error {f['marker_error'] * 1000:.3f} mm, "
          f"fit {f['seconds']:.1f} s, {report['total_seconds']:.1f} s in all")
    return 0


# The landmark model's points on the head drawn like the photo lie within this share of the
# eye distance (RMS) from its points on the photo, or the head is not to be trusted.
MAX_RENDER_POINTS_SHARE = 0.1


# A photo is looked at no larger than this (long side, pixels): the texture is 1024 texels
# square, and a 36-megapixel photo would cost gigabytes for nothing.
MAX_PHOTO_SIDE = 2048


def _photo_pixels(image):
    """read_photo's pixels of an open PIL image (closed here)."""
    import numpy as np
    from PIL import Image, ImageOps

    with image:
        image.draft("RGB", (MAX_PHOTO_SIDE, MAX_PHOTO_SIDE))  # a JPEG decodes at a fraction of its size
        image = ImageOps.exif_transpose(image)
        if image.mode in ("I", "I;16", "I;16B", "I;16L", "I;16N"):  # 16-bit grey: keep its range
            grey = np.asarray(image, dtype=np.float64)
            image = Image.fromarray(np.clip(grey * 255.0 / max(float(grey.max()), 1.0), 0, 255).astype(np.uint8))
        image = image.convert("RGB")
        if max(image.size) > MAX_PHOTO_SIDE:
            k = MAX_PHOTO_SIDE / max(image.size)
            image = image.resize((max(1, round(image.size[0] * k)), max(1, round(image.size[1] * k))),
                                 Image.LANCZOS)
        return np.asarray(image, dtype=np.uint8).copy()


def read_photo(path: str):
    """(h, w, 3) uint8 RGB pixels of an image file, turned upright by its EXIF orientation,
    16-bit images brought to 8 bits, scaled down to MAX_PHOTO_SIDE on its long side;
    ValueError naming the file when it is not an image."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        # a large photo (more than about 89 megapixels) is read like any other, scaled down,
        # without Pillow's two-line warning about it on stderr; one past twice that is refused
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            return _photo_pixels(Image.open(path))
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: a folder, not an image") from None
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise ValueError(f"{path}: not an image fae can read (expected JPEG or PNG; {exc})") from exc


def photo_head(template, image, photo_name: str = "photo", template_name: str = "template"):
    """(model, report): the textured head of a photo (h, w, 3) uint8 as `fae adapt --photo`
    makes it, before calibration: the landmark model's points on the photo (turned by
    quarters when needed) and on the template, fae.adapt.photo.head_from_photo, then the
    result drawn like the photo and looked at again (report["verdict"] lists what is not
    to be trusted). Raises PhotoRefused, or LandmarkModelMissing without MediaPipe."""
    from fae.adapt.photo import PhotoRefused
    from fae.render.landmarks import detect_points_all_turns, template_points

    found = detect_points_all_turns(image)
    if not found:
        raise PhotoRefused(f"{photo_name}: no face found (a face seen from the front, its eyes at least "
                           "20 pixels apart, is needed)")
    on_template = template_points(template)
    if on_template is None:
        raise PhotoRefused(f"{template_name}: the landmark model finds no face on the template")
    # the face found in each turn of the photo, the most level first, until one reads as
    # the same face when its head is drawn like the photo (a false face never does)
    first = None  # what the most level face gave, the answer when no face reads as itself
    for points, turns in found:
        try:
            model, report = _photo_head_from(template, image, points, on_template, photo_name)
        except PhotoRefused as exc:  # that face cannot make a head; another turn's may
            first = first or exc
            continue
        report["photo_quarter_turns"] = turns
        if not report["verdict"]:
            return model, report
        first = first or (model, report)
    if isinstance(first, PhotoRefused):
        raise first
    return first


def _photo_head_from(template, image, points, on_template, photo_name: str):
    """(model, report) of photo_head for the landmark model's points (468, 3) on the photo."""
    import numpy as np

    from fae.adapt.photo import PhotoPoints, head_from_photo
    from fae.render.landmarks import (EYE_POINTS, EYES, FACE_OVAL, INNER_LIP_POINTS, MOUTH_OPENING,
                                      OUTER_LIP_POINTS, points_on_render)

    size = (image.shape[1], image.shape[0])
    model, report = head_from_photo(
        template, image, PhotoPoints(points, size), on_template,
        skip=(EYE_POINTS, INNER_LIP_POINTS, OUTER_LIP_POINTS), eyes=EYES, outline=FACE_OVAL,
        holes=(EYES[0], EYES[1], MOUTH_OPENING), photo_name=photo_name)
    # the result, drawn as the photo was taken, must read as the same face
    seen = points_on_render(model, size)
    eye_px = report["eye_distance_px"]
    share = None if seen is None else float(np.sqrt(np.mean(np.sum((seen[:, :2] - points[:, :2]) ** 2, axis=1)))
                                            / eye_px)
    report["render_points_share_of_eye_distance"] = share
    verdict = []
    if share is None:
        verdict.append("the landmark model finds no face on the head drawn like the photo")
    elif share > MAX_RENDER_POINTS_SHARE:
        verdict.append(f"the head drawn like the photo puts the face's points {share * 100:.0f} % of the eye "
                       f"distance from the photo's (RMS; at most {MAX_RENDER_POINTS_SHARE * 100:.0f} %)")
    if report["folded_triangles"]:
        verdict.append(f"{report['folded_triangles']} skin triangles folded")
    report["verdict"] = verdict
    return model, report


def _run_photo(args, started: float) -> int:
    """`fae adapt --photo FACE.jpg -o HEAD.glb`: see fae.adapt.photo."""
    from fae.adapt.photo import PhotoRefused
    from fae.commands.common import overwritten_input

    if args.landmarks or args.method != "surface" or args.plot or args.levels is not None or args.feature_search:
        _say("--landmarks, --method, --plot, --levels and --feature-search belong to scans; a photo's points "
             "are found by the landmark model")
        return 2
    outputs = {"-o": args.output, "--report": args.report, "--compare": args.compare}
    problem = overwritten_input(outputs, {"photo": args.photo, "--template": args.template}) or _outputs_problem(outputs)
    if problem:
        _say(problem)
        return 2
    try:
        image = read_photo(args.photo)
        template = _read_template(args.template, args.force)
    except (OSError, ValueError) as exc:
        _say(str(exc))
        return 2
    from fae.render.landmarks import LandmarkModelMissing

    try:
        model, report = photo_head(template, image, args.photo, args.template)
        verdict = report["verdict"]
        share = report["render_points_share_of_eye_distance"]
    except LandmarkModelMissing as exc:
        _say(str(exc).replace("finding feature points on a scan", "a head from a photo")
             .replace(" (or give --landmarks)", ""))
        return 2
    except PhotoRefused as exc:
        _say(str(exc))
        return 2
    except (RuntimeError, ImportError, OSError) as exc:  # no OpenGL to draw the template with
        _say(f"cannot render the template to find its face ({exc}); is OSMesa installed (make install)?")
        return 2
    if _refused(args, args.photo, verdict, report):
        return 2
    model = _calibrated_if_whole(args, args.photo, model, report, template.fap_mapping)
    if model is None:
        return 2
    picture = None
    if args.compare:  # drawn before anything is written: a failure here leaves nothing behind
        from fae.render.compare import photo_comparison_image

        try:
            picture = photo_comparison_image(model, image)
        except (RuntimeError, ImportError, OSError, ValueError) as exc:
            _say(f"cannot draw {args.compare} ({exc})")
            return 2
    report["total_seconds"] = time.perf_counter() - started
    _write_outputs(args, model, report, picture)
    seen = "finds no face on it" if share is None else \
        f"sees it {share * 100:.1f} % of the eye distance from the photo's points (RMS)"
    print(f"{args.output}: head from {args.photo} ({report['eye_distance_px']:.0f} pixels between the eyes, turned "
          f"{report['yaw_deg']:.0f} degrees); the landmark model {seen}; {report['total_seconds']:.1f} s")
    return 0
