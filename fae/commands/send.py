"""`fae send FILE.fap`: stream a .fap file to a fae server frame by frame and report.

Prints frames acknowledged, errors, frames/s and latency (send -> pose ready) p50/p99.
Exit 0 when every frame was acknowledged, 1 when the server rejected any, 2 when the file
cannot be read or the server cannot be reached.
"""

from __future__ import annotations

import asyncio
import sys

from fae.commands.common import fail
from fae.net.client import send_fap
from fae.net.server import DEFAULT_HOST, DEFAULT_PORT


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "send", help="stream a .fap file to a fae server and report acks and latency",
        description="Send FILE.fap to `fae serve` one frame at a time (native protocol) and report "
        "acknowledgements, frames/s and latency p50/p99. Exit 1 if the server rejected frames, 2 if "
        "what answered is not a fae server or closed before answering the whole stream.")
    parser.add_argument("path", metavar="FILE.fap")
    parser.add_argument("--host", default=DEFAULT_HOST)
    parser.add_argument("--port", type=int, default=DEFAULT_PORT)
    parser.add_argument("--rate", choices=("realtime", "max"), default="realtime",
                        help="realtime: at the stream's fps (default); max: as fast as the server takes them")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for any one reply")
    parser.set_defaults(func=run)


def run(args) -> int:
    if not 0 <= args.port <= 65535:
        return fail("send", f"--port {args.port}: expected 0..65535")
    if not args.timeout > 0:
        return fail("send", f"--timeout {args.timeout:g}: expected a positive number of seconds")
    try:
        with open(args.path, encoding="utf-8", errors="replace") as handle:
            text = handle.read()
    except OSError as exc:
        return fail("send", f"{args.path}: {exc.strerror or exc}")
    try:
        report = asyncio.run(send_fap(text, args.host, args.port, rate=args.rate, timeout=args.timeout))
    except ValueError as exc:
        return fail("send", f"{args.path}: {exc}")
    except (OSError, asyncio.TimeoutError) as exc:
        return fail("send", f"{args.host}:{args.port}: {exc or 'no reply'}")
    problem = report.problem()
    if problem:
        return fail("send", f"{args.host}:{args.port}: {problem}")
    for line in report.errors[:20]:
        print(f"fae send: server: {line}", file=sys.stderr)
    if len(report.errors) > 20:
        print(f"fae send: ... {len(report.errors) - 20} more errors", file=sys.stderr)
    print(f"{args.path}: {report.summary()}")
    return 0 if report.complete else 1
