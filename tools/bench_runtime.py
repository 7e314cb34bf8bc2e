"""Frames/s of the per-frame runtime on the shipped head: FAP frame -> skin positions.

    .venv/bin/python tools/bench_runtime.py [--frames 100] [--numpy-frames 8] [--head FILE] [--device cuda]

For each real stream (fap_streams/expressions.fap; ../shared/data/fap/xface_joy.fap when
present) the Player plays `--frames` frames at the stream's rate on one CPU core (Warp
kernels: FAPs -> controls -> substeps -> skin positions), `--passes` times (the median
pass is reported: a shared machine's other load makes single passes vary by 1.5x), then
the same frames' controls are stepped by the numpy reference solver (fae.sim.reference,
same scheme and substeps) and turned into skin positions, in the same run. Prints
frames/s of both, by wall clock and by this process's CPU time (which the machine's other
load does not stretch), their ratios, and the solver's substeps per frame. Last, the same
frames on a Player whose skin has no fold guard (`fold_passes` 0: no fold guard, crease
smoothing or lip contact, fae.sim.folds), for what the guard costs; and on the Player's
"fdt" engine (FaceDefTables baked from the physics, fae.animate.bake: a multiply-add per
frame, no solver), whose error against the physics tools/bench_fdt.py measures. A head
without baked tables (the shipped one) is baked first (about a minute; `fae bake` stores
them, `--head BAKED.glb` uses them). `--device cuda` also times a Player whose skin runs on
the GPU, against the CPU Player, and reports how far apart their skins get.
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import time
from pathlib import Path

import numpy as np

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core for both (Warp's CPU kernels run on one thread)

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def streams() -> list[Path]:
    out = [REPO / "fap_streams" / "expressions.fap"]
    joy = REPO.parent / "shared" / "data" / "fap" / "xface_joy.fap"
    if joy.exists():
        out.append(joy)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--numpy-frames", type=int, default=8)
    ap.add_argument("--passes", type=int, default=5, help="timed passes over the frames (the median is reported)")
    ap.add_argument("--head", default=None, help="FaceModel .glb (default: the generic head)")
    ap.add_argument("--device", choices=("cuda",), default=None, help="also time the Player with its skin on "
                    "the GPU, against the CPU Player, and the largest gap between their skins")
    args = ap.parse_args(argv)

    from fae.data import shipped_head_path
    from fae.animate.player import Player, playable_head
    from fae.io.fap import read_fap
    from fae.io.facemodel_gltf import read_facemodel
    from fae.io.frames import dense_frames
    from fae.sim.build import skin_positions
    from fae.sim.reference import ReferenceSolver
    from fae.sim.solver import substep_count

    face = read_facemodel(args.head or shipped_head_path())
    t0 = time.perf_counter()
    player = Player(playable_head(face))
    print(f"head: {args.head or shipped_head_path().name}, {player.sim.particle_count} particles, "
          f"{player.sim.spring_count} springs; Player ready in {time.perf_counter() - t0:.1f} s")
    ref = ReferenceSolver(player.sim)
    bare = copy.copy(face)
    bare.layer_params = {**(face.layer_params or {}), "fold_passes": 0}
    unguarded = Player(playable_head(bare))
    t0 = time.perf_counter()
    fdt = Player(playable_head(face, engine="fdt"))
    print(f"fdt Player ready in {time.perf_counter() - t0:.1f} s ({len(fdt.tables)} FaceDefTables, "
          f"{fdt.facedef.entry_count} vertex entries)")

    def timed(p, frames, fps) -> tuple[list[float], list[float]]:
        p.fps = fps
        p.reset()
        p.step(frames[0])  # warm-up: kernel load
        walls, cpus = [], []
        for _ in range(args.passes):
            p.reset()
            t0, c0 = time.perf_counter(), time.process_time()
            for f in frames:
                p.step(f, dt=1.0 / fps)
            walls.append(len(frames) / (time.perf_counter() - t0))
            cpus.append(len(frames) / max(time.process_time() - c0, 1e-9))
        return walls, cpus

    on_gpu = Player(playable_head(face, device=args.device)) if args.device else None
    for path in streams():
        stream = read_fap(path)
        fps = float(stream.header.fps)
        frames = [f for _, f in zip(range(args.frames), dense_frames(stream))]
        walls, cpus = timed(player, frames, fps)
        warp_fps, warp_cpu = float(np.median(walls)), float(np.median(cpus))

        # numpy: the same controls, the same substeps, the same skin positions
        q = player.sim.particle_q.numpy().astype(np.float64)
        qd = np.zeros_like(q)
        R, t = np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3))
        n = min(args.numpy_frames, len(frames))
        t0, c0 = time.perf_counter(), time.process_time()
        for f in frames[:n]:
            activation, jaw = player.controls.controls(player.frame_values(f))
            J = player.rig.jaw(*jaw)
            R[1], t[1] = J[:3, :3], J[:3, 3]
            q, qd = ref.step(q, qd, activation, R, t, 1.0 / fps)
            skin_positions(player.sim, q, R, t)
        numpy_fps = n / (time.perf_counter() - t0)
        numpy_cpu = n / max(time.process_time() - c0, 1e-9)
        print(f"{path.name}: {len(frames)} frames at {fps:g} fps, {substep_count(player.sim, 1.0 / fps)} substeps/frame: "
              f"warp {warp_fps:.1f} frames/s (median of {args.passes} passes, {min(walls):.0f}-{max(walls):.0f}; "
              f"CPU time {warp_cpu:.0f}), numpy {numpy_fps:.2f} (CPU time {numpy_cpu:.2f}), "
              f"ratio {warp_fps / numpy_fps:.1f}x (CPU time {warp_cpu / numpy_cpu:.1f}x)")
        bare_walls, bare_cpus = timed(unguarded, frames, fps)
        print(f"  without the fold guard: {np.median(bare_walls):.1f} frames/s (CPU time {np.median(bare_cpus):.0f}); "
              f"the guard costs {100 * (1 - warp_cpu / np.median(bare_cpus)):.0f} % of the CPU frame rate")
        if on_gpu is not None:
            dev_walls, _ = timed(on_gpu, frames, fps)
            player.reset()
            on_gpu.reset()
            gap = max(float(np.abs(player.step(f, dt=1.0 / fps) - on_gpu.step(f, dt=1.0 / fps)).max()) for f in frames)
            print(f"  skin on {args.device}: {np.median(dev_walls):.0f} frames/s ({min(dev_walls):.0f}-{max(dev_walls):.0f}), "
                  f"{np.median(dev_walls) / warp_fps:.1f}x the CPU Player; skins at most {gap * 1e3:.2f} mm apart")
        fdt_walls, fdt_cpus = timed(fdt, frames, fps)
        print(f"  fdt engine (baked FaceDefTables, no solver): {np.median(fdt_walls):.0f} frames/s "
              f"({min(fdt_walls):.0f}-{max(fdt_walls):.0f}; CPU time {np.median(fdt_cpus):.0f}), "
              f"{np.median(fdt_walls) / warp_fps:.1f}x the physics (CPU time {np.median(fdt_cpus) / warp_cpu:.1f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
