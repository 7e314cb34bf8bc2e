"""Benchmark `fae serve`: frames/s ingested and latency (frame sent -> pose ready), 1 and 10 clients.

Baseline, measured in the same run: the same face stepped directly in-process (no sockets,
no parsing). Throughput runs send as fast as the server takes frames; latency runs pace
each client at --paced-fps so queues stay short (latency at full speed is queueing time).

    .venv/bin/python tools/bench_serve.py                      # Player on the shipped head
    .venv/bin/python tools/bench_serve.py --face linear        # protocol cost only

`--face linear` replaces the Player by a linear blend (rest + values @ basis) over as many
vertices as the head has (or --vertices): it measures the server, not the animation.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fae.io.fap import FapParser  # noqa: E402
from fae.io.frames import dense_frames  # noqa: E402
from fae.net.client import send_fap, split_fap_text  # noqa: E402
from fae.net.faces import Pose  # noqa: E402
from fae.net.server import FapServer  # noqa: E402

FAP = ROOT.parent / "shared" / "data" / "fap" / "xface_anger.fap"


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
    while time.perf_counter() - t0 < seconds:
        face.step(dense[n % len(dense)], 1 / 25)
        n += 1
    return n / (time.perf_counter() - t0)


async def served(factory, clients: int, text: str, rate: str):
    server = FapServer(factory, port=0)
    await server.start()
    viewer = server.subscribe(maxsize=8)  # a lossy subscriber, as a viewer would be
    t0 = time.perf_counter()
    reports = await asyncio.gather(*[send_fap(text, port=server.port, rate=rate, timeout=120) for _ in range(clients)])
    wall = time.perf_counter() - t0
    await server.close()
    viewer.close()
    assert all(r.complete for r in reports), [r.summary() for r in reports if not r.complete]
    frames = sum(r.frames_ok for r in reports)
    lat = np.concatenate([r.latencies for r in reports]) * 1e3
    return frames / wall, np.percentile(lat, 50), np.percentile(lat, 99)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--face", choices=("player", "linear"), default="player")
    ap.add_argument("--head", default=str(ROOT / "templates" / "generic_head.glb"))
    ap.add_argument("--vertices", type=int, default=0, help="linear face size (default: the head's, else 20000)")
    ap.add_argument("--frames", type=int, default=2000, help="frames per client in throughput runs")
    ap.add_argument("--paced-fps", type=float, default=100.0, help="per-client rate in latency runs")
    args = ap.parse_args()
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
        from fae.net.faces import player_face_factory
        factory, what = player_face_factory(model), f"Player on {Path(args.head).name} ({model.skin_vertex_count} skin vertices)"
    else:
        n = args.vertices or (model.skin_vertex_count if model is not None else 20000)
        factory, what = (lambda: LinearFace(n)), f"linear face, {n} vertices (protocol cost only)"
    print(f"face: {what}")
    text = long_stream(args.frames, 25)
    base = direct_rate(factory, text)
    print(f"baseline, face stepped directly in-process: {base:,.0f} frames/s")
    for clients in (1, 10):
        fps, p50, p99 = asyncio.run(served(factory, clients, text if clients == 1 else long_stream(args.frames // 4, 25), "max"))
        print(f"{clients:2d} client(s), max rate: {fps:,.0f} frames/s ingested ({fps / base:.2f}x baseline), "
              f"latency p50 {p50:.2f} ms p99 {p99:.2f} ms (includes queueing)")
    for clients in (1, 10):
        paced = long_stream(int(args.paced_fps * 3), args.paced_fps)
        fps, p50, p99 = asyncio.run(served(factory, clients, paced, "realtime"))
        print(f"{clients:2d} client(s), paced {args.paced_fps:g} frames/s each: {fps:,.0f} frames/s, "
              f"latency p50 {p50:.2f} ms p99 {p99:.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
