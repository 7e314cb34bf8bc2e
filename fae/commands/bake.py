"""`fae bake [HEAD.glb] -o BAKED.glb`: FaceDefTables baked from the head's own physics.

Every low-level FAP that moves the skin (3-22, 31-42, 51-68) is held alone at the borders
of its table (a few values per sign across the range the player clamps to) until the skin
settles; the settled displacements become MPEG-4 FaceDefTables in the head's FaceDefTable
slot (fae.animate.bake). `fae play --engine fdt` then plays the head through the tables
alone. The input head is never modified; the output appears only when complete. Exit
status 0 on success, 2 for a bad head, FAP list or output path.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

from fae.commands.common import fail, load_head, os_error_text, output_problem


def register(subparsers) -> None:
    parser = subparsers.add_parser("bake", help="bake FaceDefTables from a head's physics into a new .glb",
                                   description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    parser.add_argument("head", nargs="?", default=None, metavar="HEAD.glb",
                        help="FaceModel .glb (default: the shipped generic head)")
    parser.add_argument("-o", "--output", required=True, metavar="BAKED.glb", help="the baked head to write")
    parser.add_argument("--faps", default=None, help="comma-separated FAP numbers, ranges or names to bake, e.g. 3,19-22,open_jaw "
                        "(default: every FAP that moves the skin)")
    parser.add_argument("--intervals", type=int, default=None, metavar="N",
                        help="table intervals per sign of a FAP's range (default 3)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fae.animate.bake import INTERVALS_PER_SIDE
    from fae.mpeg4.faptables import SKIN_TRANSLATION_FAPS
    from fae.commands.verify_faps import parse_fap_list
    from fae.io.facemodel_gltf import FaceModelError, write_facemodel

    intervals = INTERVALS_PER_SIDE if args.intervals is None else args.intervals
    if not 1 <= intervals <= 32:
        return fail("bake", f"--intervals {intervals}: expected 1..32 intervals per sign")
    try:
        # "" (an empty shell variable) is a mistake, not "all": 45 s of baking every FAP
        faps = parse_fap_list(args.faps) if args.faps is not None else list(SKIN_TRANSLATION_FAPS)
    except ValueError as exc:
        return fail("bake", str(exc))
    wrong = [k for k in faps if k not in SKIN_TRANSLATION_FAPS]
    if wrong:
        return fail("bake", f"--faps: FAP {wrong[0]} does not move the skin (expected numbers in 3-22, 31-42, 51-68)")
    problem = output_problem(args.output, ".glb")
    if problem:
        return fail("bake", problem)
    try:
        face, head = load_head(args.head)
    except FaceModelError as exc:
        return fail("bake", str(exc))
    if Path(args.output).resolve() == head.resolve():
        return fail("bake", f"{args.output}: is the input head; expected another file name (inputs are never modified)")

    t0 = time.perf_counter()
    with contextlib.redirect_stdout(sys.stderr):  # Warp's banner and kernel-load lines
        from fae.animate.bake import bake_tables, baked_model
        from fae.animate.player import Player, playable_head

        try:
            player = Player(playable_head(face))
        except (RuntimeError, ValueError) as exc:  # data the engine cannot use (fae template check says which)
            return fail("bake", f"{head}: cannot animate it: {exc}")

        def progress(done: int, total: int) -> None:
            if sys.stderr.isatty():
                print(f"\rfae bake: {done}/{total} FAPs", end="", file=sys.stderr, flush=True)

        tables = bake_tables(player, faps, intervals_per_side=intervals, progress=progress)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    try:
        write_facemodel(baked_model(player.face, tables, faps), args.output)
    except OSError as exc:
        return fail("bake", os_error_text(exc))
    entries = sum(len(t.vertices) for t in tables)
    print(f"{args.output}: {len(tables)} FaceDefTables ({entries} vertex entries, {intervals} intervals per sign) "
          f"baked from {head.name} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0
