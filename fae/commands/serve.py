"""`fae serve`: play FAP streams that arrive over TCP (native line protocol and Xface tasks).

See docs/protocol.md. Stops cleanly on SIGINT/SIGTERM: connections are closed, and the
--record video is finished and moved into place. --live also serves the live view's page
and WebSocket (fae.net.view) on --http-port; --view stays the camera of --record, as in
`fae play` and `fae render`.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import sys
from pathlib import Path

from fae.commands.common import (add_device_argument, add_view_arguments, drawn_skin_colors, fail, load_head,
                                 output_problem, render_size_problem, video_size_problem, warp_device)
from fae.io.frames import MAX_HOLD_SECONDS
from fae.net.server import DEFAULT_HOST, DEFAULT_PORT, FapServer, ServerLimits


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "serve", help="play FAP streams sent over TCP (native protocol and Xface tasks)",
        description="Listen for FAP streams: native clients send a .fap stream line by line and get "
        "'ok <frame>' per frame; Xface clients send <task> messages (UPLOAD_FAP, LOAD_FAP, RESUME/STOP/"
        "REWIND_PLAYBACK). Each native client drives its own face; Xface clients share one. See "
        "docs/protocol.md.")
    parser.add_argument("--host", default=DEFAULT_HOST, help=f"address to listen on (default {DEFAULT_HOST})")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT}; 0: any)")
    parser.add_argument("--head", metavar="HEAD.glb",
                        help="face model to animate (default: the shipped generic head)")
    parser.add_argument("--record", metavar="OUT.mp4", help="render what plays into this mp4, one whole stream "
                        "after another, each pose held until the next; written when the server stops")
    add_view_arguments(parser, "640x480")  # of the --record video
    parser.add_argument("--fap-dir", metavar="DIR", help="folder Xface LOAD_FAP may read .fap files from "
                        "(default: LOAD_FAP is refused)")
    parser.add_argument("--live", action="store_true", help="also serve a live view: a page on --host showing "
                        "every face as it moves (WebGL, three.js from npm), frames over a WebSocket")
    parser.add_argument("--http-port", type=int, default=8080, metavar="PORT",
                        help="port of the live view's page (default 8080; 0: any)")
    add_device_argument(parser)
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


async def _serve(args, head) -> int:
    from fae.net.faces import player_face_factory

    model = head.face
    limits = ServerLimits(idle_timeout=args.idle_timeout, max_clients=args.max_clients,
                          max_per_address=args.max_per_address)
    server = FapServer(player_face_factory(head), args.host, args.port,
                       fap_dir=args.fap_dir, spare_faces=1, limits=limits)
    recorder = None
    if args.record:
        from fae.net.record import StreamRecorder
        from fae.render.renderer import FaceRenderer

        recorder = StreamRecorder(server.subscribe(maxsize=64, lossless=True), args.record,
                                  lambda: FaceRenderer(model, args.size, args.view, supersample=args.supersample,
                                                       show_bones=args.show_bones), args.size)
    view = None
    if args.live:
        from fae.net.view import LiveView

        try:
            view = LiveView(model, server.subscribe, args.host, args.http_port,
                            skin_colors=drawn_skin_colors(model))
        except FileNotFoundError as exc:
            return fail("serve", f"--live: {exc}")
    await server.start()
    if view is not None:
        try:
            await view.start()
        except OSError as exc:
            await server.close()
            return fail("serve", f"--live: cannot listen on {args.host}:{args.http_port} ({exc.strerror or exc})")
        print(f"fae serve: live view on {view.url}", file=sys.stderr, flush=True)
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
    if view is not None:
        await view.close()
    if recorder is not None:
        await recorder.close()
        if not recorder.frames_written:  # an empty video is not written (it said it wrote 0 frames to it)
            print(f"fae serve: no frames were played; {args.record} was not written", file=sys.stderr)
            return 0
        print(f"fae serve: wrote {recorder.frames_written} frames to {args.record}"
              + (f" ({recorder.skipped} frames of concurrent streams not recorded)" if recorder.skipped else "")
              + (f" ({recorder.gaps_cut} gaps between frames cut to {MAX_HOLD_SECONDS:g} s)" if recorder.gaps_cut else ""),
              file=sys.stderr)
    return 0


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="fae serve: %(message)s")
    if args.record:
        problem = output_problem(args.record, ".mp4")
        if problem:
            return fail("serve", f"--record {problem}")
        problem = video_size_problem(args.size) or render_size_problem(args.size, args.supersample)
        if problem:
            return fail("serve", problem)
    if not args.idle_timeout > 0:
        return fail("serve", f"--idle-timeout {args.idle_timeout:g}: expected a positive number of seconds")
    for flag, port in (("--port", args.port), ("--http-port", args.http_port)):
        if not 0 <= port <= 65535:
            return fail("serve", f"{flag} {port}: expected 0..65535")
    for flag, value in (("--max-clients", args.max_clients), ("--max-per-address", args.max_per_address)):
        if value < 1:
            return fail("serve", f"{flag} {value}: expected at least 1")
    if args.fap_dir and not Path(args.fap_dir).is_dir():
        return fail("serve", f"--fap-dir {args.fap_dir}: not a folder")
    from fae.io.facemodel_gltf import FaceModelError

    try:
        device = warp_device(args.device)
    except ValueError as exc:
        return fail("serve", str(exc))
    try:
        model, head = load_head(args.head)
    except FaceModelError as exc:
        return fail("serve", f"--head {exc}")
    args.head = str(head)
    from fae.animate.player import needs_calibration, playable_head

    try:
        if needs_calibration(model):
            print(f"fae serve: {args.head} carries no FAP mapping that fits; calibrating it once (tens of seconds)",
                  file=sys.stderr, flush=True)
        playable = playable_head(model, device=device)  # shared by every client's face
    except (RuntimeError, ValueError) as exc:
        print(f"fae serve: --head {args.head}: cannot animate it: {exc}", file=sys.stderr)
        return 2
    try:
        return asyncio.run(_serve(args, playable))
    except OSError as exc:
        print(f"fae serve: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
