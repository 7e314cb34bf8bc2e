"""`fae export HEAD.glb [STREAM.fap] -o OUT.glb`: the head as a plain glTF 2.0 scene.

The scene opens in any glTF viewer: the skin (with the head's colours) and the eyes, teeth
and tongue as meshes; the head, jaw, eyes and tongue as nodes that move; the head's
FaceDefTables baked from its physics as named morph targets of the skin, one per table
interval (baked first when the head has none: minutes; `fae bake` stores them). With a
stream, one animation at the stream's rate (or --fps): the morph weights and the nodes'
poses of every frame, as `fae play --engine fdt` plays it (fae.io.export_gltf). The input
head is never modified; the output appears only when complete. Exit status 0 on success,
2 for a bad head, stream or output path.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from fae.commands.common import (MAX_SCENE_FRAMES_BYTES, drawn_skin_colors, fail, load_head, os_error_text,
                                 output_problem, timing_problem, unbaked_notice)
from fae.io.facemodel import BONES
from fae.io.frames import MAX_HOLD_SECONDS


def register(subparsers) -> None:
    parser = subparsers.add_parser("export", help="export a head (and a stream's animation) as a standard glTF scene",
                                   description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    parser.add_argument("head", metavar="HEAD.glb", help="FaceModel .glb")
    parser.add_argument("stream", nargs="?", default=None, metavar="STREAM.fap", help="a FAP stream to animate")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.glb", help="the glTF scene to write")
    parser.add_argument("--fps", type=float, default=None, help="resample the stream to this frame rate "
                        "(default: its own)")
    parser.add_argument("--max-hold", type=float, default=MAX_HOLD_SECONDS, metavar="SECONDS",
                        help=f"longest a gap in the frame numbers is held (default {MAX_HOLD_SECONDS:g})")
    parser.set_defaults(func=run)


def _keyframes_problem(stream: str, count: int, fps: float, targets: int) -> str | None:
    """Why `count` frames of `targets` morph weights and the posed nodes are too many to hold
    while the scene is made (float64 each), or None."""
    need = count * 8 * (targets + 16 * len(BONES))  # a 4x4 pose per bone and frame
    if need <= MAX_SCENE_FRAMES_BYTES:
        return None
    return (f"{stream}: {count} frames at {fps:g} fps would hold {need / 2 ** 30:.1f} GiB of keyframes while the "
            f"scene is made (at most {MAX_SCENE_FRAMES_BYTES / 2 ** 30:.0f} GiB); expected fewer frames: a shorter "
            "--max-hold for the stream's gaps, or a lower --fps (nothing written)")


def run(args: argparse.Namespace) -> int:
    from fae.io.facemodel_gltf import FaceModelError
    from fae.io.fap import FapFormatError, read_fap

    problem = timing_problem(args.fps, args.max_hold)
    if problem:
        return fail("export", problem)
    problem = output_problem(args.output, ".glb")
    if problem:
        return fail("export", problem)
    try:
        model, head = load_head(args.head)
        stream = read_fap(args.stream) if args.stream else None
    except (FapFormatError, FaceModelError) as exc:
        return fail("export", str(exc))
    if Path(args.output).resolve() in {head.resolve(), *([Path(args.stream).resolve()] if args.stream else [])}:
        return fail("export", f"{args.output}: is an input file; expected another file name (inputs are never modified)")

    from fae.animate.bake import has_baked_tables
    from fae.io.export_gltf import write_scene
    from fae.io.frames import dense_frames

    frames = fps = None
    if stream is not None:  # its length first: a scene too large is refused before any bake or play
        fps = float(args.fps) if args.fps else float(stream.header.fps)
        frames = dense_frames(stream, fps=args.fps, max_hold=args.max_hold)
        try:
            count = frames.count()  # from the frame numbers alone: a gap held for days is counted at once
        except FapFormatError as exc:
            return fail("export", f"{exc} (nothing written)")
        if count == 0:
            return fail("export", f"{args.stream}: no frames to animate; expected at least one frame after the "
                        "header (nothing written)")
        problem = _keyframes_problem(args.stream, count, fps, 0)  # the poses alone
        if problem:
            return fail("export", problem)
    if not has_baked_tables(model):
        print(f"fae export: {head.name} has no baked FaceDefTables; baking them first (minutes; "
              "`fae bake` stores them)", file=sys.stderr)
    with contextlib.redirect_stdout(sys.stderr):  # Warp's banner and kernel-load lines
        from fae.animate.morphs import keyframes, morph_targets
        from fae.animate.player import Player, playable_head

        try:
            player = Player(playable_head(model, engine="fdt"))
        except (RuntimeError, ValueError) as exc:  # data the engine cannot use (fae template check says which)
            return fail("export", f"{head}: cannot animate it: {exc}")
        notice = unbaked_notice("export", str(head), player.head.faps_without_tables, stream) if stream else None
        if notice:
            print(notice, file=sys.stderr)
        targets = morph_targets(player.tables)
        animation = None
        if frames is not None:
            problem = _keyframes_problem(args.stream, count, fps, len(targets))
            if problem:
                return fail("export", problem)
            try:
                animation = keyframes(player, targets, frames, fps)
            except FapFormatError as exc:
                return fail("export", f"{exc} (nothing written)")
    try:
        write_scene(args.output, player.face, targets=targets, skin_colors=drawn_skin_colors(player.face),
                    keyframes=animation, name=head.stem)
    except OSError as exc:
        return fail("export", os_error_text(exc))
    if frames is not None:
        for warning in stream.warnings + frames.warnings:
            print(f"fae export: warning: {warning}", file=sys.stderr)
    what = f"{len(animation.times)} frames at {fps:g} fps" if animation is not None else "no animation"
    print(f"{args.output}: glTF scene of {head.name}, {len(targets)} morph targets, {what}", file=sys.stderr)
    return 0
