"""The `fae` command line: one sub-command per module in :mod:`fae.commands`.

Each command module exposes ``register(subparsers)``, which adds its parser and sets
``func(args) -> int`` (the exit status). Modules are imported lazily by name so that
`fae --help` stays fast and a broken optional stack (OpenGL, Warp) only affects the
commands that need it.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading

from fae import __version__

# Module names under fae.commands, in the order `fae --help` lists them.
COMMANDS = (
    "inspect",
    "adapt",
    "serve",
    "send",
    "render",
    "play",
    "batch",
    "bake",
    "export",
    "template",
    "verify_faps",
    "verify_skin",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fae",
        description="MPEG-4 Facial Animation engine: play .fap streams on a generic or "
        "personalized head, adapt the template to a scan, render headless.",
    )
    parser.add_argument("--version", action="version", version=f"fae {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"fae.commands.{name}").register(sub)
    return parser


class Terminated(BaseException):
    """SIGTERM arrived: unwinds like Ctrl-C (outputs half-written are removed on the way)."""


def _terminate(signum, frame) -> None:
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # SIGTERM's default is to die on the spot, leaving temporary outputs behind; as an
    # exception it unwinds through their clean-up. (`fae serve` installs its own.)
    installed = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if installed else None
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("fae: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("fae: terminated", file=sys.stderr)
        return 143
    except BrokenPipeError:
        return 0
    finally:
        if installed:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def run() -> None:
    """The `fae` command's entry point: main(), then exit at once.

    Everything a command writes is closed and renamed before main returns; what Python's
    teardown does after that (freeing Warp's kernel modules and arrays, MediaPipe's graph,
    OSMesa's context) took 0.2-0.7 s of every command on two cores (`fae adapt` of a bust
    0.6-0.7 s), which a user waits for and nothing needs. The exit handlers still run, and the
    usual exit is kept where something may still need the teardown: under a profiler or a
    tracer (coverage writes its data then), or with a thread of the command still running
    (the idle threads that split Warp's launches over the cores are let go first: kept, they
    had made every `fae adapt` take the usual exit)."""
    code = main()
    split = sys.modules.get("fae.warp_setup")  # (not imported for a command without Warp)
    if split is not None:
        split.stop_split_pools()  # idle kernel-launch threads, which would keep the usual exit
    quick = (sys.gettrace() is None and sys.getprofile() is None
             and all(t.daemon or t is threading.main_thread() for t in threading.enumerate()))
    if not quick:
        sys.exit(code)
    import atexit
    import os

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except BrokenPipeError:  # the reader left: nothing more to say (as main treats it)
            pass
        except (OSError, ValueError) as exc:
            # what was printed did not all arrive (a full disk): as Python's own exit, 120
            if stream is sys.stdout and sys.stderr is not None:
                try:
                    print(f"fae: could not write the output: {exc}", file=sys.stderr, flush=True)
                except (OSError, ValueError):
                    pass
            code = code or 120
    os._exit(code)


if __name__ == "__main__":
    run()
