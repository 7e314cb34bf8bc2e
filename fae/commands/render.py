"""`fae render [HEAD.glb] -o OUT.png`: a still of a head at rest (the shipped one by default).

Exit status 0 on success, 2 for a bad head, output path or size.
"""

from __future__ import annotations

import argparse
import sys

from fae.commands.common import (add_view_arguments, fail, load_head, memory_message, os_error_text,
                                 output_problem, render_size_problem)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "render", help="render a still PNG of a head at rest",
        description="Render a FaceModel .glb (the shipped generic head when omitted) at rest "
        "into a PNG. The file appears only when complete.")
    parser.add_argument("head", nargs="?", metavar="HEAD.glb", help="FaceModel .glb (default: the shipped generic head)")
    parser.add_argument("-o", "--output", required=True, metavar="OUT.png", help="the image to write")
    add_view_arguments(parser, "640x480")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fae.io.facemodel_gltf import FaceModelError

    problem = output_problem(args.output, ".png") or render_size_problem(args.size, args.supersample)
    if problem:
        return fail("render", problem)
    try:
        model, head = load_head(args.head)
    except FaceModelError as exc:
        return fail("render", str(exc))
    from fae.render.png import write_png
    from fae.render.renderer import FaceRenderer

    try:
        with FaceRenderer(model, size=args.size, view=args.view, supersample=args.supersample,
                          show_bones=args.show_bones) as renderer:
            image = renderer.render()
        write_png(args.output, image, sweep=True)
    except MemoryError:  # a large render holds about five copies of its pixels (8192x8192 x2: 10 GB)
        return fail("render", memory_message(args.size, args.supersample))
    except OSError as exc:  # the output refused (a full disk): OutputError names the file
        return fail("render", os_error_text(exc))
    print(f"{args.output}: {head.name}, {args.view} view, {args.size[0]}x{args.size[1]}", file=sys.stderr)
    return 0
