"""What several commands share: saying why they stop, image sizes, output paths, the head.

    fail(command, message, status=2) -> status   the reason on stderr, as `fae COMMAND: ...`
    parse_size("640x480") -> (640, 480)           argparse type for --size (parse_supersample: --supersample)
    output_problem(path, ".mp4") -> str | None   why an output file cannot be written there
    video_size_problem((w, h)) -> str | None     why frames of that size cannot be encoded
    timing_problem(fps, max_hold) -> str | None  why --fps or --max-hold cannot be used
    load_head(path | None) -> (FaceModel, Path)  --head, or the shipped generic head
    add_view_arguments(parser, "640x480")        --size, --view, --supersample, --show-bones
    add_device_argument(parser)                  --device cpu | cuda | auto (the skin's Warp device)
    warp_device("auto") -> "cuda" | "cpu"         --device resolved; ValueError when CUDA is asked and absent
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

from fae.io.atomic import special_file


MAX_SCENE_FRAMES_BYTES = 2 * 2 ** 30  # what a glTF scene's frames (shapes, keyframes) may hold while it is made


def fail(command: str, message: str, status: int = 2) -> int:
    """Print `fae COMMAND: MESSAGE` on stderr and return the exit status (2: bad input)."""
    print(f"fae {command}: {message}", file=sys.stderr)
    return status


def parse_size(text: str) -> tuple[int, int]:
    """'640x480' -> (640, 480); argparse type: bad text exits 2 with the reason."""
    from fae.batch.jobs import size_numbers

    size = size_numbers(text)
    if size is None:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT in pixels, e.g. 640x480")
    w, h = size
    if w <= 0 or h <= 0 or w > 8192 or h > 8192:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be between 1 and 8192 pixels")
    return w, h


def parse_supersample(text: str) -> int:
    """'2' -> 2; argparse type for --supersample (1..8: the cost grows as its square)."""
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number 1..8") from None
    if not 1 <= k <= 8:
        raise argparse.ArgumentTypeError(f"{text}: expected 1..8")
    return k


def output_problem(path: str, suffix: str | None = None) -> str | None:
    """Why `path` cannot receive an output file (with `suffix`, when given), or None when it can."""
    target = Path(path)
    if suffix is not None and target.suffix.lower() != suffix:
        return f"{path}: expected a {suffix} file name"
    if target.is_dir():
        return f"{path}: is a folder, expected a {suffix or 'file'} name"
    kind = special_file(target)
    if kind is not None:  # the output's rename would replace it with a plain file
        return f"{path}: is {kind}, not a file; expected a {suffix or 'file'} name to write"
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


def timing_problem(fps: float | None, max_hold: float | None = None) -> str | None:
    """Why --fps (frames/s, None: the stream's own) or --max-hold (seconds) cannot be used."""
    from fae.io.fap import MIN_FPS

    if fps is not None and not (MIN_FPS <= fps <= 1000):
        return f"--fps {fps:g}: expected a frame rate in [{MIN_FPS:g}, 1000]"
    if max_hold is not None and not 0 <= max_hold <= 1e6:
        return f"--max-hold {max_hold:g}: expected seconds in [0, 1e6]"
    return None


def render_size_problem(size: tuple[int, int], supersample: int) -> str | None:
    """Why an image of `size` rendered at `supersample` x that size cannot be drawn: a side
    past MAX_RENDER_SIDE (which also keeps its buffer, 4 bytes a pixel, under OpenGL's 2 GiB,
    past which the process died)."""
    from fae.render.framing import MAX_RENDER_SIDE

    width, height = size
    if max(width, height) * supersample > MAX_RENDER_SIDE:
        return (f"--size {width}x{height} with --supersample {supersample}: the image rendered "
                f"({width * supersample}x{height * supersample}) is too large; expected at most {MAX_RENDER_SIDE} "
                "pixels a side (a smaller --size or --supersample)")
    return None


def memory_message(size: tuple[int, int], supersample: int) -> str:
    """What to say when a render of `size` at `supersample` ran out of memory."""
    width, height = size
    copy = width * supersample * height * supersample * 4 / 2**30
    return (f"--size {width}x{height} with --supersample {supersample}: not enough memory (the render holds "
            f"about five copies of its {copy:.2g} GiB of pixels); expected a smaller --size or --supersample, "
            "or more memory")


def video_size_problem(size: tuple[int, int]) -> str | None:
    """Why frames of `size` cannot be encoded as H.264 (it needs an even width and height)."""
    width, height = size
    if width % 2 or height % 2:
        return f"--size {width}x{height}: H.264 video needs an even width and height"
    return None


def load_head(path: str | os.PathLike | None):
    """(FaceModel, path) of the head at `path`, or of the shipped generic head when None.

    Raises FaceModelError naming the file: missing, unreadable or inconsistent.
    """
    from fae.data import TEMPLATES_VARIABLE, shipped_head_path
    from fae.io.facemodel_gltf import FaceModelError, read_facemodel

    head = Path(path) if path else shipped_head_path()
    if head.is_dir():
        raise FaceModelError(f"{head}: a folder; expected a head file (.glb)")
    if not head.is_file():
        if path:
            what = "head file"
        elif os.environ.get(TEMPLATES_VARIABLE):
            what = f"shipped generic head (${TEMPLATES_VARIABLE} names its folder)"
        else:
            what = "shipped generic head (pass --head HEAD.glb, or build it with `fae template build`)"
        raise FaceModelError(f"{head}: {what} not found")
    return read_facemodel(head), head


def unbaked_notice(command: str, head_name: str, without_tables: list[int], stream,
                   head_path: str | None = None) -> str | None:
    """The notice for FAPs `stream` (a FapStream) sets that a head baked for some FAPs only
    plays without moving the skin (`without_tables`: PlayableHead.faps_without_tables), or
    None; head_path: the head's file, for the `fae bake` it suggests (default: head_name,
    or HEAD.glb where that is no file). A stream that cannot be read gets None here: playing
    it reports why."""
    if not without_tables:
        return None
    from fae.animate.highlevel import faps_in_stream
    from fae.io.fap import FapFormatError

    try:
        missing = sorted(faps_in_stream(stream) & set(without_tables))
    except FapFormatError:
        return None
    if not missing:
        return None
    numbers = ",".join(str(k) for k in missing)
    many = len(missing) > 1
    head_path = head_path or (head_name if os.path.isfile(head_name) else "HEAD.glb")
    return (f"fae {command}: {head_name}: FAP{'s' if many else ''} {numbers} of the stream {'have' if many else 'has'} "
            f"no FaceDefTable on this head (baked for some FAPs only): the tables leave the skin still for "
            f"{'them' if many else 'it'}; bake {'them' if many else 'it'} too (`fae bake {head_path} -o BAKED.glb "
            f"--faps ...` with every FAP wanted, or without --faps for all)"
            + (" or play with --engine physics" if command == "play" else ""))


def add_view_arguments(parser: argparse.ArgumentParser, default_size: str) -> None:
    """The camera and image options of the commands that render (play, render)."""
    from fae.render.framing import VIEWS

    parser.add_argument("--size", type=parse_size, default=parse_size(default_size), metavar="WxH",
                        help=f"image size in pixels (default {default_size})")
    parser.add_argument("--view", choices=list(VIEWS), default="front", help="camera preset (default front)")
    parser.add_argument("--supersample", type=parse_supersample, default=1, metavar="K",
                        help="render at K x size and average (anti-aliasing; costs about K^2)")
    parser.add_argument("--show-bones", action="store_true",
                        help="also draw the cranium and mandible (hidden under the skin; for checking how it sits)")


DEVICES = ("cpu", "cuda", "auto")


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """--device: where the skin's Warp kernels run per frame."""
    parser.add_argument("--device", choices=DEVICES, default="cpu",
                        help="where the skin is simulated: cpu (default), cuda (an NVIDIA GPU), or auto "
                        "(cuda when one is present, else cpu)")


def warp_device(name: str) -> str:
    """The Warp device of --device `name`: "cpu", or "cuda" when asked for (or for "auto")
    and a CUDA device is present. ValueError when "cuda" is asked for and there is none."""
    if name not in DEVICES:
        raise ValueError(f"--device {name}: expected one of {', '.join(DEVICES)}")
    if name == "cpu":
        return "cpu"
    from fae.warp_setup import wp

    if wp.is_cuda_available():
        return "cuda"
    if name == "cuda":
        raise ValueError("--device cuda: no CUDA device found (Warp sees no NVIDIA GPU and driver); "
                         "use --device cpu or auto")
    return "cpu"


def drawn_skin_colors(model):
    """(V, 3) linear RGB of the skin as fae draws it (the mouth's lining darker), or None
    when the renderer's module cannot be loaded (no OpenGL): the skin's own colour then."""
    try:
        from fae.render.renderer import skin_colors
    except Exception:  # an OpenGL stack that fails to import: the colours are a nicety
        return None
    return skin_colors(model)


def overwritten_input(outputs: dict[str, str | None], inputs: dict[str, str | None]) -> str | None:
    """A reason when an output path is one of the input files or another output, or None."""
    def same(a: str, b: str) -> bool:
        if os.path.exists(a) and os.path.exists(b):
            return os.path.samefile(a, b)
        return os.path.realpath(a) == os.path.realpath(b)

    given = [(flag, out) for flag, out in outputs.items() if out]
    for i, (flag, out) in enumerate(given):  # -o H.glb --report H.glb wrote the report over the head
        for other_flag, other in given[i + 1:]:
            if same(out, other):
                return f"{other_flag} {other}: the same file as {flag}; expected a file of its own"
    for out_flag, out in outputs.items():
        for in_name, src in inputs.items():
            if out and src and same(out, src):
                return (f"{out_flag} {out}: would overwrite the {in_name}; expected a new file (inputs are "
                        "never overwritten)")
    return None


def os_error_text(exc: OSError) -> str:
    """One line for an OSError: its own words when it names the file itself (OutputError,
    messages written for the user), else the file it names and what went wrong."""
    return str(exc) if exc.filename is None else f"{exc.filename}: {exc.strerror}"


def json_safe(value):
    """`value` (dicts, lists, numbers, numpy scalars and arrays) with non-finite floats as
    null: JSON has no Infinity or NaN, and strict readers (JavaScript's JSON.parse) refuse them."""
    import math

    import numpy as np

    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    return value


def json_text(value, indent: int | None = None) -> str:
    """`value` as strict JSON text (non-finite numbers as null, json_safe)."""
    import json

    return json.dumps(json_safe(value), indent=indent, allow_nan=False)
