"""Benchmark `fae serve`: frames/s ingested and latency (frame sent -> pose ready), 1 and 10 clients.

Baseline, measured in the same run: the same face stepped directly in-process (no sockets,
no parsing), one step per frame. The clients run in a separate process from the server.
Throughput runs send as fast as the server takes frames; paced runs send each client's
frames at each rate of --paced-fps (25 frames/s, the sample streams' own, and 100).
Paced clients start together (in phase: every client's frame k is sent at the same moment,
the worst case) and, in a second run, at random moments within one frame period, as
independent programs would. Latency is frame sent -> its `ok` read (positions ready).
When frames arrive faster than a face steps, the server coalesces them (one step with the
latest held values; see docs/protocol.md): the output shows frames vs face steps.

    .venv/bin/python tools/bench_serve.py                      # Player on the shipped head
    .venv/bin/python tools/bench_serve.py --face linear        # protocol cost only

`--face linear` replaces the Player by a linear blend (rest + values @ basis) over as many
vertices as the head has (or --vertices): it measures the server, not the animation.
"""

from __future__ import annotations

import os

# Several faces step in threads of one process: BLAS thread pools of their own only fight
# over the cores (a 9k-vertex linear step: 2 ms with one BLAS thread, 16 ms with a pool on a
# busy 2-core machine). Set before numpy loads; the client process inherits it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import asyncio  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fae.data import shipped_head_path  # noqa: E402
from fae.io.fap import FapParser  # noqa: E402
from fae.io.frames import dense_frames  # noqa: E402
from fae.net.client import send_fap, split_fap_text  # noqa: E402
from fae.net.faces import Pose  # noqa: E402
from fae.net.server import FapServer  # noqa: E402

# a real stream where the data is beside the project, else a shipped one
FAP = next(p for p in (ROOT.parent / "shared" / "data" / "fap" / "xface_anger.fap", ROOT / "fap_streams" / "expressions.fap")
           if p.is_file())


class LinearFace:
    def __init__(self, vertices: int) -> None:
        rng = np.random.default_rng(0)
        self.rest = rng.normal(size=(vertices, 3)) * 0.05
        self.basis = rng.normal(size=(68, vertices * 3)) * 1e-6

    def step(self, frame, dt):
        return Pose(self.rest + (frame.values @ self.basis).reshape(-1, 3), {})

    def reset(self):
        pass


def long_stream(frames: int, fps: float) -> str:
    """The sample file's frames repeated and renumbered to `frames` frames at `fps`."""
    header, pairs = split_fap_text(FAP.read_text())
    lines = [f"2.1 bench {fps:g} {frames}"]
    for k in range(frames):
        mask, values = pairs[k % len(pairs)]
        lines += [mask, f"{k} " + values.split(maxsplit=1)[1]]
    return "\n".join(lines) + "\n"


def direct_rate(factory, text: str, seconds: float = 2.0) -> float:
    parser = FapParser("bench")
    frames = [f for n, ln in enumerate(text.splitlines(), 1) if (f := parser.feed_line(ln, n)) is not None]
    dense = list(dense_frames(frames, source_fps=parser.header.fps))
    face = factory()
    t0, n = time.perf_counter(), 0
    while n < 5 or time.perf_counter() - t0 < seconds:
        face.step(dense[n % len(dense)], 1 / 25)
        n += 1
    return n / (time.perf_counter() - t0)


async def served(factory, clients: int, text: str, rate: str, spare_faces: int = 0, phases: str = "same"):
    """Serve `clients` concurrent streams of `text` sent by a separate client process
    (`phases` "same": all start at once; "random": each within one frame period)."""
    server = FapServer(factory, port=0, spare_faces=spare_faces)
    await server.start()
    viewer = server.subscribe(maxsize=8)  # a lossy subscriber, as a viewer would be
    with tempfile.NamedTemporaryFile("w", suffix=".fap", delete=False) as handle:
        handle.write(text)
    try:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, __file__, "--client", handle.name, "--port", str(server.port),
            "--clients", str(clients), "--rate", rate, "--phases", phases,
            stdout=asyncio.subprocess.PIPE)
        out, _ = await proc.communicate()
    finally:
        Path(handle.name).unlink()
        await server.close()
        viewer.close()
    if proc.returncode != 0:
        raise RuntimeError(f"bench client failed ({proc.returncode})")
    result = json.loads(out)
    stats = server.stats()
    return result["frames_per_s"], result["p50_ms"], result["p99_ms"], stats["native_frames"], stats["native_steps"]


async def client_main(path: str, port: int, clients: int, rate: str, phases: str = "same") -> dict:
    """The client side: `clients` concurrent streams of one file; frames/s and latency."""
    text = Path(path).read_text()
    parser = FapParser(path)
    parser.feed_line(split_fap_text(text)[0], 1)
    period = 1.0 / parser.header.fps
    offsets = np.random.default_rng(7).uniform(0.0, period, clients) if phases == "random" else np.zeros(clients)

    async def one(offset: float):
        await asyncio.sleep(offset)
        return await send_fap(text, port=port, rate=rate, timeout=300)

    t0 = time.perf_counter()
    reports = await asyncio.gather(*[one(float(o)) for o in offsets])
    wall = time.perf_counter() - t0
    bad = [r.summary() for r in reports if not r.complete]
    if bad:
        raise RuntimeError(f"incomplete streams: {bad}")
    # Frames/s from the first frame sent to the last ack, per client (face set-up excluded).
    first = min(r.started for r in reports)
    last = max(r.started + r.elapsed for r in reports)
    lat = np.concatenate([r.latencies for r in reports]) * 1e3
    return {"frames_per_s": sum(r.frames_ok for r in reports) / (last - first), "wall_s": wall,
            "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--face", choices=("player", "linear"), default="player")
    ap.add_argument("--head", default=str(shipped_head_path()))
    ap.add_argument("--vertices", type=int, default=0, help="linear face size (default: the head's, else 20000)")
    ap.add_argument("--frames", type=int, default=2000, help="frames per client in throughput runs")
    ap.add_argument("--paced-seconds", type=float, default=10.0,
                    help="length of each paced run (p99 of 1 client at 25 frames/s: the 3rd worst of 250 frames)")
    ap.add_argument("--paced-fps", default="25,100",
                    help="per-client rates in latency runs (comma-separated; 25: the sample streams' own)")
    ap.add_argument("--client", metavar="FILE.fap", help=argparse.SUPPRESS)  # the client process
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--clients", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--rate", default="max", help=argparse.SUPPRESS)
    ap.add_argument("--phases", default="same", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.client:
        print(json.dumps(asyncio.run(client_main(args.client, args.port, args.clients, args.rate, args.phases))))
        return 0
    if not FAP.is_file():
        print(f"bench_serve: {FAP} not found", file=sys.stderr)
        return 2
    model = None
    if Path(args.head).is_file():
        from fae.io.facemodel_gltf import read_facemodel
        model = read_facemodel(args.head)
    if args.face == "player":
        if model is None:
            print(f"bench_serve: {args.head} not found (use --face linear to measure the protocol alone)", file=sys.stderr)
            return 2
        from fae.animate.player import playable_head
        from fae.net.faces import player_face_factory
        factory, what = player_face_factory(playable_head(model)), f"Player on {Path(args.head).name} ({model.skin_vertex_count} skin vertices)"
    else:
        n = args.vertices or (model.skin_vertex_count if model is not None else 20000)
        factory, what = (lambda: LinearFace(n)), f"linear face, {n} vertices (protocol cost only)"
    print(f"face: {what}")
    text = long_stream(args.frames, 25)
    base = direct_rate(factory, text)
    print(f"baseline, face stepped directly in-process: {base:,.1f} frames/s")
    for clients in (1, 10):
        stream = text if clients == 1 else long_stream(args.frames // 4, 25)
        fps, p50, p99, frames, steps = asyncio.run(served(factory, clients, stream, "max", spare_faces=clients))
        print(f"{clients:2d} client(s), max rate: {fps:,.0f} frames/s ingested ({fps / base:.2f}x baseline), "
              f"{frames} frames in {steps} face steps, latency p50 {p50:.2f} ms p99 {p99:.2f} ms")
    for rate in (float(r) for r in args.paced_fps.split(",")):
        for clients, phases in ((1, "same"), (10, "same"), (10, "random")):
            paced = long_stream(max(int(rate * args.paced_seconds), 10), rate)
            fps, p50, p99, frames, steps = asyncio.run(served(factory, clients, paced, "realtime", spare_faces=clients,
                                                              phases=phases))
            how = "" if clients == 1 else (" in phase" if phases == "same" else " at random phases")
            print(f"{clients:2d} client(s), paced {rate:g} frames/s each{how}: {fps:,.0f} frames/s, "
                  f"{frames} frames in {steps} face steps, latency p50 {p50:.2f} ms p99 {p99:.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
