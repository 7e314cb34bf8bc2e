"""`fae inspect FILE.fap [--json]`: what a .fap stream holds and whether fae understands it.

Exit status 0 when the file is understood (with or without warnings), 2 when it is
rejected or missing (the reason, naming file and line, on stderr).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from fae.commands.common import fail
from fae.io.fap import FapFormatError, read_fap
from fae.mpeg4.faps import FAP_COUNT, FAPS
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


def summarize(path: str) -> dict:
    """Read `path` fully (streaming) and return the summary dict; raises FapFormatError."""
    stream = read_fap(path)
    ever = np.zeros(FAP_COUNT, dtype=bool)
    low = np.full(FAP_COUNT, np.inf)
    high = np.full(FAP_COUNT, -np.inf)
    first_number = last_number = None
    visemes: set[int] = set()
    expressions: set[int] = set()
    for frame in stream:
        if first_number is None:
            first_number = frame.number
        last_number = frame.number
        ever |= frame.mask
        sent = frame.mask
        low[sent] = np.minimum(low[sent], frame.values[sent])
        high[sent] = np.maximum(high[sent], frame.values[sent])
        if frame.viseme is not None:
            visemes.update((frame.viseme.select1, frame.viseme.select2))
        if frame.expression is not None:
            expressions.update((frame.expression.select1, frame.expression.select2))
    header = stream.header
    used = [int(i) + 1 for i in np.flatnonzero(ever)]
    frame_count = stream.frame_count or 0
    span = (last_number - first_number + 1) if first_number is not None else 0
    return {
        "path": str(path),
        "version": header.version,
        "name": header.name,
        "fps": header.fps,
        "frame_count": frame_count,
        "declared_frame_count": header.declared_frame_count,
        "first_frame_number": first_number,
        "last_frame_number": last_number,
        "duration_s": span / header.fps,
        "faps_used": used,
        "value_ranges": {str(n): [float(low[n - 1]), float(high[n - 1])] for n in used},
        "visemes_used": sorted(visemes),
        "expressions_used": sorted(expressions),
        "warnings": list(stream.warnings),
    }


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
        summary = summarize(args.path)
    except FapFormatError as exc:
        return fail("inspect", str(exc))
    if args.json:
        print(json.dumps(summary))
    else:
        print(_text(summary))
    return 0
