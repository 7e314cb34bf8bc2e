"""`fae play STREAM.fap [--head HEAD.glb] -o OUT.mp4`: animate a head and encode the video.

The shipped generic head is used when --head is absent. The video has the stream's frame
rate (or --fps, resampled by the player) and appears only when complete: a stream that
turns out malformed part-way leaves no partial file. Exit status 0 on success, 2 for bad
input (stream, head, output path, size), 1 when encoding fails.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import fae
from fae.io.frames import MAX_HOLD_SECONDS

TEMPLATE_NAME = "generic_head.glb"


def default_head_path() -> Path:
    """The shipped generic head: `<repo>/templates/generic_head.glb` beside the `fae` package,
    else `fae/data/generic_head.glb` (an installed copy), else `$FAE_TEMPLATES/generic_head.glb`.

    Returns the first existing candidate, or the repository path (for the error message).
    """
    package = Path(fae.__file__).resolve().parent
    candidates = []
    if os.environ.get("FAE_TEMPLATES"):
        candidates.append(Path(os.environ["FAE_TEMPLATES"]) / TEMPLATE_NAME)
    candidates += [package.parent / "templates" / TEMPLATE_NAME, package / "data" / TEMPLATE_NAME,
                   Path(sys.prefix) / "share" / "fae" / "templates" / TEMPLATE_NAME]
    for path in candidates:
        if path.is_file():
            return path
    return package.parent / "templates" / TEMPLATE_NAME


def parse_size(text: str) -> tuple[int, int]:
    """'640x480' -> (640, 480); argparse type: bad text exits 2 with the reason."""
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT in pixels, e.g. 640x480") from None
    if w <= 0 or h <= 0 or w > 8192 or h > 8192:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be between 1 and 8192 pixels")
    return w, h


def output_problem(path: str, suffix: str | None = None) -> str | None:
    """Why `path` cannot receive an output file (with `suffix`, when given), or None when it can."""
    target = Path(path)
    if suffix is not None and target.suffix.lower() != suffix:
        return f"{path}: expected a {suffix} file name"
    if target.is_dir():
        return f"{path}: is a folder, expected a {suffix or 'file'} name"
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        return f"{path}: output folder {folder} does not exist"
    if not os.access(folder, os.W_OK):
        return f"{path}: output folder {folder} is not writable"
    try:  # the one sure test (root passes os.access everywhere, /proc takes no files)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        return f"{path}: output folder {folder} cannot take a file ({exc.strerror or exc})"
    return None


def load_head(path: str | None):
    """(FaceModel, path) of --head or the shipped template; raises FaceModelError."""
    from fae.io.facemodel_gltf import FaceModelError, read_facemodel

    head = Path(path) if path else default_head_path()
    if not head.is_file():
        what = "head file" if path else "shipped generic head (pass --head HEAD.glb)"
        raise FaceModelError(f"{head}: {what} not found")
    return read_facemodel(head), head


def add_view_arguments(parser: argparse.ArgumentParser, default_size: str) -> None:
    from fae.render.framing import VIEWS

    parser.add_argument("--size", type=parse_size, default=parse_size(default_size), metavar="WxH",
                        help=f"image size in pixels (default {default_size})")
    parser.add_argument("--view", choices=list(VIEWS), default="front", help="camera preset (default front)")
    parser.add_argument("--supersample", type=int, default=1, metavar="K",
                        help="render at K x size and average (anti-aliasing; costs about K^2)")
    parser.add_argument("--show-bones", action="store_true",
                        help="also draw the cranium and mandible (hidden under the skin; for checking how it sits)")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "play", help="animate a head from a .fap stream into an H.264 mp4",
        description="Play a .fap stream on a head (the shipped generic head unless --head) and "
        "write an H.264 mp4 at the stream's frame rate. The file appears only when complete.")
    parser.add_argument("stream", metavar="STREAM.fap", help="the FAP stream to play")
    parser.add_argument("--head", metavar="HEAD.glb", help="FaceModel .glb (default: the shipped generic head)")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.mp4", help="the video to write")
    add_view_arguments(parser, "640x480")
    parser.add_argument("--fps", type=float, default=None, help="resample to this frame rate (default: the stream's)")
    parser.add_argument("--max-hold", type=float, default=MAX_HOLD_SECONDS, metavar="SECONDS",
                        help=f"longest a gap in the frame numbers is held (default {MAX_HOLD_SECONDS:g}); a longer "
                        "gap is cut to it, with a warning, so that no stream plays for ever")
    parser.add_argument("--frames-dir", metavar="DIR", help="also write each frame as DIR/frame_00000.png, ...")
    parser.set_defaults(func=run)


def _fail(message: str, status: int = 2) -> int:
    print(f"fae play: {message}", file=sys.stderr)
    return status


def run(args: argparse.Namespace) -> int:
    from fae.io.facemodel_gltf import FaceModelError
    from fae.io.fap import FapFormatError, read_fap

    width, height = args.size
    if width % 2 or height % 2:
        return _fail(f"--size {width}x{height}: H.264 video needs an even width and height")
    if args.supersample < 1 or args.supersample > 8:
        return _fail(f"--supersample {args.supersample}: expected 1..8")
    if args.fps is not None and not (0 < args.fps <= 1000):
        return _fail(f"--fps {args.fps:g}: expected a frame rate in (0, 1000]")
    if not 0 <= args.max_hold <= 1e6:
        return _fail(f"--max-hold {args.max_hold:g}: expected seconds in [0, 1e6]")
    problem = output_problem(args.output, ".mp4")
    if problem:
        return _fail(problem)
    frames_dir = None
    if args.frames_dir:
        frames_dir = Path(args.frames_dir)
        try:
            frames_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            return _fail(f"{frames_dir}: cannot create the frames folder ({exc.strerror or exc})")
    try:
        stream = read_fap(args.stream)
        model, _ = load_head(args.head)
    except (FapFormatError, FaceModelError) as exc:
        return _fail(str(exc))

    from fae.animate.player import Player
    from fae.io.frames import dense_frames
    from fae.render.play import render_video
    from fae.render.renderer import FaceRenderer
    from fae.render.video import VideoError

    fps = float(args.fps) if args.fps else float(stream.header.fps)
    expected = round(stream.header.declared_frame_count * fps / stream.header.fps)
    progress = None
    if sys.stderr.isatty():
        from tqdm import tqdm

        progress = tqdm(total=expected or None, unit="frame", desc=Path(args.output).name, file=sys.stderr)
    try:
        with FaceRenderer(model, size=(width, height), view=args.view, supersample=args.supersample,
                          show_bones=args.show_bones) as renderer:
            player = Player(model, device="cpu")
            frames = dense_frames(stream, fps=args.fps, max_hold=args.max_hold)
            timings = render_video(player.play(frames, fps=fps), renderer, args.output, fps,
                                   frames_dir=frames_dir,
                                   on_frame=(lambda n: progress.update(1)) if progress else None)
    except FapFormatError as exc:
        return _fail(f"{exc} (no video written)")
    except VideoError as exc:
        return _fail(str(exc), status=1)
    except OSError as exc:  # the output folder refused the file (OutputError names it)
        return _fail(str(exc) if exc.filename is None else f"{exc.filename}: {exc.strerror}")
    finally:
        if progress is not None:
            progress.close()
    for warning in frames.warnings:
        print(f"fae play: warning: {warning}", file=sys.stderr)
    print(f"{args.output}: {timings.frames} frames at {fps:g} fps, {width}x{height} "
          f"({timings.fps:.1f} frames/s)", file=sys.stderr)
    return 0
