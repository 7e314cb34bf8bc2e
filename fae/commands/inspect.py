"""`fae inspect FILE.fap [--json]`: what a .fap stream holds and whether fae understands it.

Exit status 0 when the file is understood (with or without warnings), 2 when it is
rejected or missing (the reason, naming file and line, on stderr).
"""

from __future__ import annotations

import argparse
import os

from fae.commands.common import fail, json_text
from fae.io.fap import FapFormatError
from fae.io.fap_summary import summarize_fap
from fae.mpeg4.faps import FAPS
from fae.mpeg4.highlevel import EXPRESSIONS, VISEMES


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "inspect", help="summarize a .fap stream (header, frames, FAPs used, warnings)",
        description="Read a .fap stream and summarize it: version, name, fps, frames, the FAPs it "
        "drives and their value ranges, and anything fae accepted with a warning. Exit 0 when "
        "understood, 2 when rejected.")
    parser.add_argument("path", metavar="FILE.fap", help="the .fap file to read")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    parser.set_defaults(func=run)


def _text(summary: dict) -> str:
    lines = [
        f"{summary['path']}: .fap version {summary['version']}, name {summary['name']!r}",
        f"  {summary['frame_count']} frames (header declares {summary['declared_frame_count']}) at "
        f"{summary['fps']:g} fps = {summary['duration_s']:.2f} s",
        f"  FAPs used ({len(summary['faps_used'])}):",
    ]
    for number in summary["faps_used"]:
        low, high = summary["value_ranges"][str(number)]
        info = FAPS[number - 1]
        unit = info.fapu or "code"
        lines.append(f"    {number:2d} {info.name:<22s} {low:>10g} .. {high:<10g} {unit}")
    if summary["visemes_used"]:
        lines.append("  visemes: " + ", ".join(f"{c} {VISEMES[c].name}" for c in summary["visemes_used"]))
    if summary["expressions_used"]:
        lines.append("  expressions: " + ", ".join(f"{c} {EXPRESSIONS[c].name}" for c in summary["expressions_used"]))
    if summary["warnings"]:
        lines.append(f"  warnings ({len(summary['warnings'])}):")
        lines += [f"    {w}" for w in summary["warnings"]]
    else:
        lines.append("  no warnings")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if not os.path.isfile(args.path):
        reason = "is not a file" if os.path.exists(args.path) else "no such file"
        return fail("inspect", f"{args.path}: {reason}")
    try:
        summary = summarize_fap(args.path)
    except FapFormatError as exc:
        return fail("inspect", str(exc))
    if args.json:
        print(json_text(summary))
    else:
        print(_text(summary))
    return 0
