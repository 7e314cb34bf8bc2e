"""How far FaceDefTable playback (Player engine "fdt") is from the physics it was baked from.

    .venv/bin/python tools/bench_fdt.py [--head BAKED.glb] [--frames 500] [STREAM.fap ...]

Without streams: fap_streams/*.fap and ../shared/data/fap/*.fap when present. Each stream
is played at its own rate by both engines from the neutral face (at most `--frames`
frames); per frame, the distance between the two skins at every vertex. Printed per
stream: mean and 95th percentile (mm) over all skin vertices of all frames, the same over
the vertices the physics moves more than 0.1 mm in that frame ("moved"), the worst
vertex, and frames/s of both engines on one core. Then FAP pairs held together until
settled against the sum of each alone (where superposition breaks). A head without baked
tables (default: the shipped head) is baked first.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

# FAP pairs a face combines (numbers; values are fractions of each FAP's positive limit)
PAIRS = [((3, 0.5), (12, 0.5)),    # open jaw + raise left lip corner
         ((3, 0.5), (5, 0.5)),     # open jaw + raise bottom mid lip
         ((4, -0.5), (5, 0.5)),    # upper lip down + lower lip up: lips pressed
         ((12, 0.5), (13, 0.5)),   # both lip corners up (smile)
         ((6, 0.5), (7, 0.5)),     # stretch both corners
         ((31, 0.5), (33, 0.5)),   # left inner + middle brow up
         ((19, 0.5), (21, 0.5))]   # left top + bottom eyelid close


def default_streams() -> list[Path]:
    out = sorted((REPO / "fap_streams").glob("*.fap"))
    shared = REPO.parent / "shared" / "data" / "fap"
    return out + (sorted(shared.glob("*.fap")) if shared.is_dir() else [])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("streams", nargs="*", type=Path)
    ap.add_argument("--head", default=None, help="FaceModel .glb (default: the shipped head, baked first)")
    ap.add_argument("--frames", type=int, default=500)
    args = ap.parse_args(argv)

    from fae.animate.bake import settled_skin
    from fae.mpeg4.faptables import FAP_LIMITS, FAP_NAME
    from fae.animate.player import Player, playable_head
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel
    from fae.io.fap import read_fap
    from fae.io.frames import dense_frames

    face = read_facemodel(args.head or shipped_head_path())
    t0 = time.perf_counter()
    fdt = Player(playable_head(face, engine="fdt"))
    print(f"head: {args.head or shipped_head_path().name}; fdt Player ready in {time.perf_counter() - t0:.1f} s "
          f"({len(fdt.tables)} tables, {fdt.facedef.entry_count} vertex entries)")
    physics = Player(playable_head(fdt.face))
    rest = np.asarray(face.skin_vertices)
    totals = []
    for path in args.streams or default_streams():
        stream = read_fap(path)
        fps = float(stream.header.fps)
        frames = [f for _, f in zip(range(args.frames), dense_frames(stream))]
        timings = {}
        skins = {}
        for name, player in (("physics", physics), ("fdt", fdt)):
            player.reset()
            player.step(frames[0], dt=1.0 / fps)  # warm-up: kernel load
            player.reset()
            t = time.process_time()
            skins[name] = [player.step(f, dt=1.0 / fps) for f in frames]
            timings[name] = len(frames) / max(time.process_time() - t, 1e-9)
        error = np.array([np.linalg.norm(a - b, axis=1) for a, b in zip(skins["fdt"], skins["physics"])]) * 1e3
        moved = np.array([np.linalg.norm(b - rest, axis=1) for b in skins["physics"]]) > 1e-4
        m = error[moved] if moved.any() else np.zeros(1)
        totals.append(error.ravel())
        print(f"{path.name}: {len(frames)} frames; error mm all vertices mean {error.mean():.3f} p95 "
              f"{np.percentile(error, 95):.3f}; moved vertices mean {m.mean():.3f} p95 {np.percentile(m, 95):.3f}; "
              f"worst {error.max():.2f}; frames/s (CPU time) fdt {timings['fdt']:.0f}, physics {timings['physics']:.0f} "
              f"({timings['fdt'] / timings['physics']:.0f}x)")
    if totals:
        e = np.concatenate(totals)
        print(f"all streams: mean {e.mean():.3f} mm, p95 {np.percentile(e, 95):.3f} mm")

    print("FAP pairs held together, settled: physics against the tables' sum (mm over the vertices either moves)")
    for (a, fa), (b, fb) in PAIRS:
        values = np.zeros(68)
        values[a - 1] = fa * FAP_LIMITS[a - 1, 1 if fa > 0 else 0] * (1 if fa > 0 else -1)
        values[b - 1] = fb * FAP_LIMITS[b - 1, 1 if fb > 0 else 0] * (1 if fb > 0 else -1)
        both = settled_skin(physics, values)
        fdt.reset()
        table = fdt.step(values)
        moved = np.linalg.norm(both - rest, axis=1) > 1e-4
        err = np.linalg.norm(table - both, axis=1)[moved] * 1e3
        motion = np.linalg.norm(both - rest, axis=1)[moved].max() * 1e3
        print(f"  {FAP_NAME[a - 1]} {values[a - 1]:+.0f} + {FAP_NAME[b - 1]} {values[b - 1]:+.0f}: mean {err.mean():.3f} "
              f"p95 {np.percentile(err, 95):.3f} worst {err.max():.2f} (largest motion {motion:.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
