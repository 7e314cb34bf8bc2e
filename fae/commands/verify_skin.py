"""`fae verify-skin [HEAD.glb] [STREAM.fap ...] [--faps LIST] [--json]`: does the skin stay whole?

Plays each stream from rest on the head (the shipped generic head unless HEAD) and checks
every frame, in the head's own frame: visible skin triangles folded (a normal turned more
than 90 degrees from its rest normal, "turned", or on a crease: two neighbours that met
smoothly at rest now more than 90 degrees apart; the mouth's lining, seen only through the
lips, left out), the worst edge stretch and compression (edge length over rest length,
limits 2 and 0.3), the lips passing through each other (an edge of one lip through a
triangle of the other), and skin hidden at rest (the eyelids' lining, the backs of the
ears, the nostrils) coming out through the visible skin ("lining": its dark back shows),
and how much of the face a viewer in front sees by the skin's back ("backs": frames over
3 mm^2, and the most, in mm^2), whatever turned it. Without streams it plays every
low-level FAP alone to the limits of its range and the standard's six expressions at full
intensity; the sweep is reported per FAP too: how far towards the standard's limit each
one, on each side, keeps the skin whole (climbing a quarter of the range at a time, each
step held until the skin settles), and what gives first. --faps sweeps only the FAPs
named (numbers, ranges or names), to look at a few closely. --pictures DIR draws, for each
stream that breaks, its worst frame with what breaks marked red: the face from the front
beside a close-up (DIR/<stream>.png). Exit status 0 when every stream keeps
the skin whole, 1 when any does not, 2 when the head or a stream cannot be read.
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
from pathlib import Path

from fae.commands.common import add_device_argument


def register(subparsers) -> None:
    parser = subparsers.add_parser("verify-skin", help="check that streams never fold or tear a head's skin",
                                   description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    parser.add_argument("head", nargs="?", default=None, metavar="HEAD.glb",
                        help="FaceModel .glb (default: the generic head)")
    parser.add_argument("streams", nargs="*", metavar="STREAM.fap",
                        help="FAP streams to play (default: the FAP sweep and the six expressions)")
    parser.add_argument("--faps", default=None, metavar="LIST",
                        help="sweep only these low-level FAPs (3-68), by number, range or name, comma-separated "
                             "(e.g. 5,open_jaw,19); instead of the default streams")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--pictures", default=None, metavar="DIR",
                        help="for each stream that breaks, write DIR/<stream>.png: its worst frame with what "
                             "breaks marked red, the face and a close-up (DIR is made if missing; a picture "
                             "of the same name there is replaced)")
    add_device_argument(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    from fae.commands.common import fail, json_text, load_head, os_error_text, warp_device
    from fae.io.facemodel_gltf import FaceModelError
    from fae.io.fap import FapFormatError, read_fap
    from fae.io.frames import dense_frames

    head, streams = args.head, list(args.streams)
    if head is not None and head.lower().endswith(".fap"):  # streams only: the shipped head
        head, streams = None, [head] + streams
    sweep_faps = None
    if args.faps is not None:
        try:
            sweep_faps = swept_faps(args.faps)
        except ValueError as exc:
            return fail("verify-skin", str(exc))
        if streams:
            return fail("verify-skin", "--faps sweeps FAPs instead of playing streams; give one or the other")
    misplaced = [s for s in streams if s.lower().endswith((".glb", ".gltf"))]
    if misplaced:
        return fail("verify-skin", f"{misplaced[0]}: a head among the streams; expected .fap streams after the head "
                    "(fae verify-skin [HEAD.glb] [STREAM.fap ...])")
    try:
        device = warp_device(args.device)
    except ValueError as exc:
        return fail("verify-skin", str(exc))
    try:
        face, path = load_head(head)
    except (OSError, FaceModelError) as exc:
        return fail("verify-skin", str(exc))
    loaded = []
    for s in streams:
        try:
            loaded.append((s, read_fap(s)))
        except FapFormatError as exc:
            return fail("verify-skin", str(exc))
        except OSError as exc:
            return fail("verify-skin", f"{s}: cannot read ({exc.strerror or exc})")
    pictures = None
    if args.pictures is not None:  # (made once the head and streams are read: no folder for a refused run)
        pictures = Path(args.pictures)
        try:
            pictures.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=pictures):  # writable: found now, not after minutes of checking
                pass
        except OSError as exc:
            return fail("verify-skin", f"--pictures {args.pictures}: cannot write pictures there "
                                       f"({exc.strerror or exc})")

    with contextlib.redirect_stdout(sys.stderr):  # Warp's banner and kernel-load lines: stdout is the report's
        from fae.animate.player import Player, playable_head
        from fae.animate.skin_check import (SkinCheck, check_stream, default_streams, fap_sweep, rounded_down,
                                            rounded_up)

        try:
            player = Player(playable_head(face, device=device))
        except (RuntimeError, ValueError) as exc:  # data the engine cannot use (fae template check says which)
            return fail("verify-skin", f"{path}: cannot animate it: {exc}")
        check = SkinCheck(player.face)
        if sweep_faps is not None:
            loaded = [(f"fap-sweep of FAPs {','.join(str(k) for k in sweep_faps)}", fap_sweep(sweep_faps))]
        elif not loaded:
            loaded = default_streams()
        reports = []
        drawn: set[str] = set()
        for name, stream in loaded:
            is_file = hasattr(stream, "header")
            frames = dense_frames(stream) if is_file else stream  # a file's: its warnings kept, at its own rate
            shown: dict | None = {} if pictures is not None else None
            try:
                reports.append(check_stream(player, frames, name, fps=stream.header.fps if is_file else None,
                                            check=check, shown=shown))
            except FapFormatError as exc:
                return fail("verify-skin", str(exc))
            if shown:
                try:
                    reports[-1]["picture"] = str(_draw(player.face, shown, pictures, name, drawn))
                except (OSError, RuntimeError) as exc:  # the report is kept: the picture alone is lost
                    why = os_error_text(exc) if isinstance(exc, OSError) else str(exc)
                    reports[-1]["picture"] = None
                    print(f"fae verify-skin: {name}: no picture: {why}", file=sys.stderr)
            elif pictures is not None and reports[-1]["frames_not_finite"] and not reports[-1]["ok"]:
                print(f"fae verify-skin: {name}: no picture: no finite frame breaks (only frames not finite)",
                      file=sys.stderr)
            if reports[-1]["frames"] == 0:
                return fail("verify-skin", f"{name}: no frames to check; expected at least one frame after the header")
            for warning in getattr(stream, "warnings", []) + getattr(frames, "warnings", []):
                print(f"fae verify-skin: warning: {warning}", file=sys.stderr)
    whole = all(r["ok"] for r in reports)
    if args.json:
        print(json_text({"head": str(path), "streams": reports, "ok": whole}, indent=1))
    else:
        print(f"{path}: folded = visible skin triangles ever turned over or on a crease (turned: their own normal "
              f"turned over); stretch / compression = "
              f"extreme edge length over rest length; lips = frames where the lips pass through each other; "
              f"lining = frames where skin hidden at rest comes out through the visible skin; backs = frames "
              f"where a viewer in front sees over 3 mm^2 of the skin's back (mm^2: the most)")
        print(f"{'stream':<44} {'frames':>6} {'folded':>7} {'turned':>6} {'(frames)':>8} {'stretch':>7} {'compr.':>6} "
              f"{'lips':>5} {'lining':>6} {'backs':>5} {'mm^2':>6}  worst regions")
        for r in reports:
            regions = [f"{k} {v}" for k, v in sorted(r["folded_by_region"].items(), key=lambda kv: -kv[1])[:4]]
            if r["frames_not_finite"]:
                regions.insert(0, f"{r['frames_not_finite']} frames not finite (NaN or inf)")
            if r["frames_back_shown"]:
                back = sorted(r["back_by_region"].items(), key=lambda kv: -kv[1])[:2]
                regions.append(f"back at frame {r['worst_back_frame']}: " + ", ".join(f"{k} {v:.0f} mm^2" for k, v in back))
            regions = ", ".join(regions)
            print(f"{_column(str(r['stream'])):<44} {r['frames']:>6} {r['triangles_folded']:>7} {r['triangles_turned']:>6} "
                  f"{r['frames_folded']:>8} "
                  f"{rounded_up(r['max_stretch'], 2):>7.2f} {rounded_down(r['min_compression'], 2):>6.2f} {r['frames_lips_crossed']:>5} "
                  f"{r['frames_lining_shown']:>6} {r['frames_back_shown']:>5} {r['max_back_area_mm2']:>6.0f}  {regions}")
        for r in reports:
            if "per_fap" in r:
                print(per_fap_text(r))
        print("the skin stays whole" if whole else
              "the skin folds, tears, the lips cross, a lining or the skin's back shows, or it is not finite: see above")
    return 0 if whole else 1


def _draw(face, shown: dict, folder: Path, name: str, drawn: set[str]) -> Path:
    """Write the picture of a stream's worst frame (check_stream's `shown`) into `folder`,
    named after the stream (`drawn`: the names taken so far, each picture its own file)."""
    import re

    from fae.render.png import write_png
    from fae.render.problems import problem_image

    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(name).stem if name.endswith(".fap") else name)[:80] or "stream"
    file, k = f"{stem}.png", 1
    while file.casefold() in drawn:  # (one file on a filesystem that ignores case)
        k += 1
        file = f"{stem}-{k}.png"
    drawn.add(file.casefold())
    image = problem_image(face, shown["skin"], shown["bones"], shown["problem"], shown.get("pupil_scale"))
    path = folder / file
    write_png(path, image)
    print(f"fae verify-skin: {name}: frame {shown['index']} drawn to {path}", file=sys.stderr)
    return path


def _column(name: str, width: int = 44) -> str:
    """A stream's name in the table's first column: a long path keeps its end (the file's
    name), not its start (takes of one session differ only there)."""
    return name if len(name) <= width else "..." + name[-(width - 3):]


def swept_faps(text: str) -> list[int]:
    """Low-level FAP numbers (3-68) from "5,open_jaw,19-22" (fae.commands.verify_faps.parse_fap_list)."""
    from fae.commands.verify_faps import parse_fap_list

    faps = parse_fap_list(text)
    high_level = [k for k in faps if k < 3]
    if high_level:
        raise ValueError(f"--faps: FAP {high_level[0]}: expected a low-level FAP, 3 to 68")
    return faps


def per_fap_text(report: dict) -> str:
    """The sweep's FAPs grouped by how far towards the standard's limit they keep the skin
    whole (a few lines: each FAP as its number and side, e.g. 5+)."""
    groups: dict[float, list[str]] = {}
    for e in report["per_fap"]:
        groups.setdefault(e["whole_to"], []).append(f"{e['fap']}{e['side']}")
    lines = [f"{_column(str(report['stream']))}: how far each FAP keeps the skin whole (share of the standard's limit)"]
    for share in sorted(groups, reverse=True):
        what = "the whole range" if share == 1.0 else "not at the first quarter" if share == 0.0 else f"up to {share:g}"
        lines.append(f"  {what}: {' '.join(groups[share])}")
    worst = sorted((e for e in report["per_fap"] if e["triangles_folded"]), key=lambda e: -e["triangles_folded"])[:5]
    if worst:
        lines.append("  most folded: " + ", ".join(f"{e['fap']}{e['side']} {e['name']} {e['triangles_folded']}"
                                                  for e in worst))
    return "\n".join(lines)
