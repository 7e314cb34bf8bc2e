"""`fae play STREAM.fap [--head HEAD.glb | --head MESH --landmarks LM] -o OUT.mp4`: animate a head and encode the video.

With --landmarks, --head is any mesh (OBJ, PLY, STL, OFF, glTF: an artist's head, a scan)
and LM its MPEG-4 feature points (FDP JSON or CSV, menpo .ljson or CSV with iBUG-68): the
template is played and its motion carried over to the mesh, which keeps its own topology
(fae.animate.retarget; a few seconds of set-up for the template's fit to it). With
`-o OUT.glb` the mesh and its animation are written as a glTF scene instead of a video:
the mesh with its own UVs and texture, eyes and jaw parts on nodes that move, and the
frames' shapes as morph targets (their principal shapes, as few as rebuild every frame
within 0.1 mm: fae.animate.morphs.shape_targets) with one key per frame.

The shipped generic head is used when --head is absent; `--engine fdt` moves the skin by
the head's FaceDefTables baked from its physics (`fae bake`) instead of simulating it. The video has the stream's frame
rate (or --fps, resampled by the player) and appears only when complete: a stream that
turns out malformed part-way leaves no partial file. Exit status 0 on success, 2 for bad
input (stream, head, output path, size), 1 when encoding fails.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fae.commands.common import (MAX_SCENE_FRAMES_BYTES, add_device_argument, add_view_arguments, drawn_skin_colors,
                                 fail, load_head, memory_message, os_error_text, output_problem, overwritten_input,
                                 render_size_problem, timing_problem, unbaked_notice, video_size_problem, warp_device)
from fae.io.frames import MAX_HOLD_SECONDS


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "play", help="animate a head from a .fap stream into an H.264 mp4",
        description="Play a .fap stream on a head (the shipped generic head unless --head) and "
        "write an H.264 mp4 at the stream's frame rate. The file appears only when complete.")
    parser.add_argument("stream", metavar="STREAM.fap", help="the FAP stream to play")
    parser.add_argument("--head", metavar="HEAD", help="FaceModel .glb (default: the shipped generic head), or with "
                        "--landmarks any mesh (OBJ, PLY, STL, OFF, glTF) animated by motion transfer")
    parser.add_argument("--landmarks", metavar="LM", help="feature points of the --head mesh (JSON {\"9.3\": [x, y, z] "
                        "or vertex index}, CSV name,x,y,z, or 68 iBUG points as menpo .ljson or CSV): the template's "
                        "motion is carried over to the mesh, which keeps its own topology")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.mp4", help="the video to write; with "
                        "--landmarks, OUT.glb writes the mesh and its animation as a glTF scene instead")
    add_view_arguments(parser, "640x480")
    parser.add_argument("--fps", type=float, default=None, help="resample to this frame rate (default: the stream's)")
    parser.add_argument("--max-hold", type=float, default=MAX_HOLD_SECONDS, metavar="SECONDS",
                        help=f"longest a gap in the frame numbers is held (default {MAX_HOLD_SECONDS:g}); a longer "
                        "gap is cut to it, with a warning, so that no stream plays for ever")
    parser.add_argument("--engine", choices=("physics", "fdt"), default="physics",
                        help="physics: simulate the skin (default); fdt: move it by the head's FaceDefTables baked "
                        "from the physics (`fae bake`; a head without them is baked first, minutes)")
    add_device_argument(parser)
    parser.add_argument("--frames-dir", metavar="DIR", help="also write each frame as DIR/frame_00000.png, ...")
    parser.add_argument("--force", action="store_true", help="with --landmarks: play the mesh even when the "
                        "template's fit to it is not to be trusted (folds, a face far from the mesh)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fae.io.facemodel_gltf import FaceModelError
    from fae.io.fap import FapFormatError, read_fap

    width, height = args.size
    problem = video_size_problem(args.size) or render_size_problem(args.size, args.supersample)
    if problem:
        return fail("play", problem)
    problem = timing_problem(args.fps, args.max_hold)
    if problem:
        return fail("play", problem)
    scene = Path(args.output).suffix.lower() == ".glb"
    if args.landmarks and Path(args.output).suffix.lower() not in (".mp4", ".glb"):
        return fail("play", f"{args.output}: expected a .mp4 (video) or .glb (glTF scene) file name")
    if scene and args.frames_dir:
        return fail("play", f"--frames-dir {args.frames_dir}: frames are written with a video (-o OUT.mp4), not "
                    "with a glTF scene")
    if scene and not args.landmarks:
        return fail("play", f"{args.output}: a glTF scene of a FaceModel head is written by `fae export "
                    f"{args.head or 'HEAD.glb'} {args.stream} -o {args.output}`; `fae play` writes it only for a mesh "
                    "animated by motion transfer (--head MESH --landmarks LM)")
    problem = output_problem(args.output, ".glb" if scene else ".mp4") or overwritten_input(
        {"-o": args.output}, {"stream": args.stream, "--head": args.head, "--landmarks file": args.landmarks})
    if problem:
        return fail("play", problem)
    try:
        device = warp_device(args.device)
    except ValueError as exc:
        return fail("play", str(exc))
    frames_dir = Path(args.frames_dir) if args.frames_dir else None
    if frames_dir is not None and frames_dir.resolve() == Path(args.output).resolve():
        # (found only after the whole stream was rendered, as the video could not replace the folder)
        return fail("play", f"--frames-dir {frames_dir}: the same path as -o {args.output}; expected a folder of "
                    "its own for the frames")
    if frames_dir is not None and frames_dir.exists() and not frames_dir.is_dir():
        return fail("play", f"{frames_dir}: not a folder; expected a folder for the frames")
    retargeted = None
    normal_groups = None
    try:
        stream = read_fap(args.stream)
        if args.landmarks:
            if not args.head:
                return fail("play", f"--landmarks {args.landmarks}: give the mesh they belong to with --head MESH")
            template, _ = load_head(None)
        else:
            problem = _mesh_without_landmarks(args.head)
            if problem:
                return fail("play", problem)
            model, _ = load_head(args.head)
    except (FapFormatError, FaceModelError) as exc:
        return fail("play", str(exc))
    if args.landmarks:
        from fae.animate.retarget import RetargetError, read_target, retarget
        from fae.commands.adapt_checks import landmark_problem, scan_problem

        try:
            target = read_target(args.head, args.landmarks)
            if target.texture_missing:
                print(f"fae play: warning: {args.head}: its material names the texture {target.texture_missing}, "
                      "which cannot be read (missing or not an image); the mesh is drawn untextured", file=sys.stderr)
            # as fae adapt checks a scan: a mesh without area, or points in another unit (a
            # million times the mesh's shrank it to a point before the fit could say so)
            problem = (scan_problem(target.vertices, target.faces, args.head)
                       or landmark_problem(target.vertices, target.landmarks, args.landmarks, args.head))
            if problem:
                return fail("play", problem)
            retargeted = retarget(template, target, say=lambda msg: print(f"fae play: {msg}", file=sys.stderr))
        except RetargetError as exc:
            return fail("play", str(exc))
        verdict = retargeted.report["fit"].get("verdict") or []
        if verdict and not args.force:
            return fail("play", f"{args.head}: the template's fit to the mesh is not to be trusted ({'; '.join(verdict)}); "
                        "check that the feature points in --landmarks mark this mesh's features, in its unit, and "
                        "that the mesh covers the face without large holes or loose fins (--force plays it anyway)")
        model = retargeted.model
        normal_groups = retargeted.normal_groups  # a scan's texture seams split its vertices

    from fae.animate.player import Player, playable_head
    from fae.io.frames import dense_frames
    from fae.render.play import EmptyStreamError, render_video
    from fae.render.renderer import FaceRenderer
    from fae.render.video import VideoError

    fps = float(args.fps) if args.fps else float(stream.header.fps)  # the reader keeps a header's rate >= MIN_FPS
    if args.engine == "fdt":
        from fae.animate.bake import has_baked_tables

        if not has_baked_tables(model if retargeted is None else template):
            print("fae play: the head has no baked FaceDefTables; baking them first (minutes; "
                  "`fae bake` stores them)", file=sys.stderr)
    try:
        if retargeted is not None:
            from fae.animate.retarget import RetargetPlayer

            player = RetargetPlayer(retargeted, Player(playable_head(template, device=device, engine=args.engine)))
        else:
            player = Player(playable_head(model, device=device, engine=args.engine))
    except (RuntimeError, ValueError) as exc:  # data the engine cannot use (fae template check says which)
        which = "the template" if retargeted is not None else args.head or "the shipped head"
        return fail("play", f"{which}: cannot animate it: {exc}")
    notice = unbaked_notice("play", "the template" if retargeted is not None else args.head or "the shipped head",
                            (player.player if retargeted is not None else player).head.faps_without_tables, stream,
                            None if retargeted is not None else args.head)
    if notice:
        print(notice, file=sys.stderr)
    expected = round(stream.header.declared_frame_count * fps / stream.header.fps)  # as the header says
    if scene:
        try:  # from the frame numbers alone: a gap held for days is counted at once
            expected = dense_frames(stream, fps=args.fps, max_hold=args.max_hold).count()
        except FapFormatError as exc:
            return fail("play", f"{exc} (nothing written)")
        need = expected * player.face.skin_vertices.size * 4
        if need > MAX_SCENE_FRAMES_BYTES:
            return fail("play", f"{args.stream}: {expected} frames at {fps:g} fps of a {len(player.face.skin_vertices)}"
                        f"-vertex mesh would hold {need / 2 ** 30:.1f} GiB of shapes while the scene is made (at most "
                        f"{MAX_SCENE_FRAMES_BYTES / 2 ** 30:.0f} GiB); play fewer frames (--fps) or write a video "
                        "(-o OUT.mp4)")
        return _write_scene(args, player, stream, fps)
    made_frames_dir = frames_dir is not None and not frames_dir.exists()
    if frames_dir is not None:  # made once the inputs are known to be good
        try:
            frames_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            return fail("play", f"{frames_dir}: cannot create the frames folder ({exc.strerror or exc})")
    progress = None
    if sys.stderr.isatty():
        from tqdm import tqdm

        progress = tqdm(total=expected or None, unit="frame", desc=Path(args.output).name, file=sys.stderr)
    try:
        with FaceRenderer(model, size=(width, height), view=args.view, supersample=args.supersample,
                          show_bones=args.show_bones, normal_groups=normal_groups) as renderer:
            frames = dense_frames(stream, fps=args.fps, max_hold=args.max_hold)
            timings = render_video(player.play(frames, fps=fps), renderer, args.output, fps,
                                   frames_dir=frames_dir,
                                   on_frame=(lambda n: progress.update(1)) if progress else None)
    except FapFormatError as exc:
        return fail("play", f"{exc} (no video written)")
    except EmptyStreamError:
        return fail("play", f"{args.stream}: no frames to play; expected at least one frame after the header "
                    "(no video written)")
    except VideoError as exc:
        return fail("play", str(exc), status=1)
    except MemoryError:  # most likely the render's buffers (the simulation's arrays are small)
        return fail("play", memory_message(args.size, args.supersample) + " (no video written)")
    except OSError as exc:  # the output folder refused the file (OutputError names it)
        return fail("play", os_error_text(exc))
    finally:
        if progress is not None:
            progress.close()
        if made_frames_dir and not any(frames_dir.iterdir()):  # a failed run leaves no empty folder
            frames_dir.rmdir()
    for warning in stream.warnings + frames.warnings:
        print(f"fae play: warning: {warning}", file=sys.stderr)
    print(f"{args.output}: {timings.frames} frames at {fps:g} fps, {width}x{height} "
          f"({timings.fps:.1f} frames/s)", file=sys.stderr)
    return 0


def _write_scene(args: argparse.Namespace, player, stream, fps: float) -> int:
    """`-o OUT.glb` with --landmarks: play the stream on the target and write it as a glTF
    scene (module docstring). The skin's shapes are taken in the head node's frame, which
    carries the head's turn (the neck's partial turn is in the shapes)."""
    import numpy as np

    from fae.animate.morphs import SHAPE_TOLERANCE, Keyframes, shape_targets
    from fae.io.export_gltf import write_scene
    from fae.io.fap import FapFormatError
    from fae.io.frames import dense_frames

    rest = np.asarray(player.face.skin_vertices, dtype=np.float64)
    offsets, bones = [], {}
    try:
        frames = dense_frames(stream, fps=args.fps, max_hold=args.max_hold)
        for f in player.play(frames, fps=fps):
            H = f.bone_transforms["head"]
            offsets.append(((f.skin_vertices - H[:3, 3]) @ H[:3, :3] - rest).astype(np.float32))
            if len(offsets) * rest.size * 4 > MAX_SCENE_FRAMES_BYTES:  # more frames than the header said
                return fail("play", f"{args.stream}: more than {len(offsets) - 1} frames of this mesh's shapes do not "
                            f"fit in {MAX_SCENE_FRAMES_BYTES / 2 ** 30:.0f} GiB while the scene is made; play fewer "
                            "frames (--fps, --max-hold) or write a video (-o OUT.mp4) (nothing written)")
            for name, T in f.bone_transforms.items():
                bones.setdefault(name, []).append(T)
    except FapFormatError as exc:
        return fail("play", f"{exc} (nothing written)")
    if not offsets:
        return fail("play", f"{args.stream}: no frames to play; expected at least one frame after the header "
                    "(nothing written)")
    targets, weights, error = shape_targets(np.stack(offsets))
    if error > SHAPE_TOLERANCE:
        print(f"fae play: warning: {len(targets)} morph targets rebuild the frames only within {error * 1000:.2f} mm "
              f"(at most {SHAPE_TOLERANCE * 1000:g} mm sought): the stream moves in more ways than they hold; a "
              "video (-o OUT.mp4) shows every frame as played", file=sys.stderr)
    animation = Keyframes(np.arange(len(offsets)) / fps, weights, {k: np.asarray(v) for k, v in bones.items()})
    try:
        write_scene(args.output, player.face, targets=targets, skin_colors=drawn_skin_colors(player.face),
                    keyframes=animation, name=Path(args.head).stem)
    except OSError as exc:
        return fail("play", os_error_text(exc))
    for warning in stream.warnings + frames.warnings:
        print(f"fae play: warning: {warning}", file=sys.stderr)
    print(f"{args.output}: glTF scene of {args.head}, {len(offsets)} frames at {fps:g} fps, {len(targets)} "
          f"morph targets (every frame within {error * 1000:.3f} mm)", file=sys.stderr)
    return 0


MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off")


def _mesh_without_landmarks(head: str | None) -> str | None:
    """Why --head cannot be played without --landmarks: a plain mesh is not a FaceModel."""
    if head and Path(head).suffix.lower() in MESH_SUFFIXES:
        return (f"{head}: a mesh, not a FaceModel .glb; to animate it by motion transfer give its feature points "
                "with --landmarks LM (FDP JSON or CSV, or 68 iBUG points as .ljson or CSV)")
    return None
