"""`fae serve`: play FAP streams that arrive over TCP (native line protocol and Xface tasks).

See docs/protocol.md. Stops cleanly on SIGINT/SIGTERM: connections are closed, and the
--record video is finished and moved into place.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import sys
from pathlib import Path

from fae.net.server import DEFAULT_HOST, DEFAULT_PORT, FapServer, ServerLimits

DEFAULT_HEAD = Path(__file__).resolve().parents[2] / "templates" / "generic_head.glb"


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    return w, h


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "serve", help="play FAP streams sent over TCP (native protocol and Xface tasks)",
        description="Listen for FAP streams: native clients send a .fap stream line by line and get "
        "'ok <frame>' per frame; Xface clients send <task> messages (UPLOAD_FAP, LOAD_FAP, RESUME/STOP/"
        "REWIND_PLAYBACK). Each native client drives its own face; Xface clients share one. See "
        "docs/protocol.md.")
    parser.add_argument("--host", default=DEFAULT_HOST, help=f"address to listen on (default {DEFAULT_HOST})")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT}; 0: any)")
    parser.add_argument("--head", default=str(DEFAULT_HEAD), metavar="HEAD.glb",
                        help="face model to animate (default: the shipped generic head)")
    parser.add_argument("--record", metavar="OUT.mp4", help="render what plays into this mp4, one whole stream "
                        "after another; written when the server stops")
    parser.add_argument("--size", default="640x480", help="--record image size WIDTHxHEIGHT (default 640x480)")
    parser.add_argument("--view", default="front", help="--record camera: front, three-quarter, profile")
    parser.add_argument("--fap-dir", metavar="DIR", help="folder Xface LOAD_FAP may read .fap files from "
                        "(default: LOAD_FAP is refused)")
    parser.add_argument("--device", default="cpu", help="Warp device for the faces (default cpu)")
    defaults = ServerLimits()
    parser.add_argument("--idle-timeout", type=float, default=defaults.idle_timeout, metavar="SECONDS",
                        help="close a client silent this long with nothing in progress "
                        f"(default {defaults.idle_timeout:g})")
    parser.add_argument("--max-clients", type=int, default=defaults.max_clients, metavar="N",
                        help=f"connections at once (default {defaults.max_clients})")
    parser.add_argument("--max-per-address", type=int, default=defaults.max_per_address, metavar="N",
                        help=f"connections at once from one IP address (default {defaults.max_per_address}); when "
                        "either limit is reached, the connection idle longest makes room for a newcomer")
    parser.set_defaults(func=run)


async def _serve(args, model, player=None) -> int:
    from fae.net.faces import player_face_factory

    limits = ServerLimits(idle_timeout=args.idle_timeout, max_clients=args.max_clients,
                          max_per_address=args.max_per_address)
    server = FapServer(player_face_factory(model, args.device, first=player), args.host, args.port,
                       fap_dir=args.fap_dir, spare_faces=1, limits=limits)
    recorder = None
    if args.record:
        from fae.net.record import StreamRecorder
        from fae.render.renderer import FaceRenderer

        size = _size(args.size)
        recorder = StreamRecorder(server.subscribe(maxsize=64, lossless=True), args.record,
                                  lambda: FaceRenderer(model, size, args.view), size)
    await server.start()
    if recorder is not None:
        recorder.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    print(f"fae serve: listening on {args.host}:{server.port} (head {args.head})", file=sys.stderr, flush=True)
    await server.serve_until(stop)
    st = server.stats()
    print(f"fae serve: stopped after {st['connections']} connections; native streams: {st['native_frames']} "
          f"frames in {st['native_steps']} face steps; Xface: {st['xface_frames']} frames in "
          f"{st['xface_steps']} face steps", file=sys.stderr)
    if recorder is not None:
        await recorder.close()
        print(f"fae serve: wrote {recorder.frames_written} frames to {args.record}"
              + (f" ({recorder.skipped} frames of concurrent streams not recorded)" if recorder.skipped else ""),
              file=sys.stderr)
    return 0


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="fae serve: %(message)s")
    if args.record:
        from fae.commands.play import output_problem

        problem = output_problem(args.record, ".mp4")
        if problem:
            print(f"fae serve: --record {problem}", file=sys.stderr)
            return 2
        _size(args.size)
    if not args.idle_timeout > 0:
        print(f"fae serve: --idle-timeout {args.idle_timeout:g}: expected a positive number of seconds", file=sys.stderr)
        return 2
    for flag, value in (("--max-clients", args.max_clients), ("--max-per-address", args.max_per_address)):
        if value < 1:
            print(f"fae serve: {flag} {value}: expected at least 1", file=sys.stderr)
            return 2
    if args.fap_dir and not Path(args.fap_dir).is_dir():
        print(f"fae serve: --fap-dir {args.fap_dir}: not a folder", file=sys.stderr)
        return 2
    from fae.io.facemodel_gltf import read_facemodel

    try:
        model = read_facemodel(args.head)
    except (OSError, ValueError) as exc:
        print(f"fae serve: --head {args.head}: {exc}", file=sys.stderr)
        return 2
    player = None
    if not model.fap_mapping:  # calibrate once here, not in every client's face
        from fae.animate.player import Player

        print(f"fae serve: {args.head} carries no FAP mapping; calibrating it once (tens of seconds)",
              file=sys.stderr, flush=True)
        try:
            player = Player(model, device=args.device)  # the template of every client's face
        except (RuntimeError, ValueError) as exc:
            print(f"fae serve: --head {args.head}: cannot animate it: {exc}", file=sys.stderr)
            return 2
        model = player.face
    try:
        return asyncio.run(_serve(args, model, player))
    except OSError as exc:
        print(f"fae serve: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
