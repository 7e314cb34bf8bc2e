"""Motion-vector transfer (fae.animate.retarget): frames per second on one core.

    .venv/bin/python tools/bench_retarget.py [--target MESH --landmarks LM] [--frames 330]

The target (default: the shipped head's skin, turned 20 degrees, scaled by 1.07 and
written in millimetres, 11k vertices, with its feature points) is bound once; the
template plays fap_streams/expressions.fap and its frames are recorded; then only the
transfer (RetargetPlayer.carry: head pose off, one batched 3x3 product, one sparse gather,
the bones re-anchored) is timed over them. The baseline, measured in the same run: the
same arithmetic as a per-vertex Python loop (what the per-frame work would cost without
precomputed arrays). Printed: the set-up's seconds, the transfer's frames/s, the
baseline's, their ratio, and the template's own physics frames/s for comparison.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def default_target(folder: Path, template) -> tuple[Path, Path]:
    """The shipped head's skin in another pose, size and unit, with its feature points."""
    import trimesh

    from fae.adapt.calibration import apply_transform

    a = np.radians(20.0)
    T = np.eye(4)
    T[:3, :3] = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) * 1.07 * 1000.0
    mesh = folder / "target.obj"
    trimesh.Trimesh(apply_transform(T, template.skin_vertices), template.skin_faces, process=False).export(mesh)
    from fae.anatomy.surface_points import markup_positions

    fdp = markup_positions(template)  # where a person marks them (2.1 at the chin's lowest point)
    lm = folder / "target.csv"
    lm.write_text("".join(f"{n},{p[0]},{p[1]},{p[2]}\n" for n, p in
                          ((n, apply_transform(T, fdp[n][None])[0]) for n in fdp
                           if template.feature_points[n].part == "skin")))
    return mesh, lm


def naive_carry(rt, neutral: np.ndarray, skin: np.ndarray, head: np.ndarray) -> np.ndarray:
    """The baseline: per target vertex, a Python loop over its gather row's template
    vertices, the head pose taken off and put back per vertex too."""
    out = np.array(rt.model.skin_vertices, dtype=np.float64, copy=True)
    G = rt.gather
    Hinv = np.linalg.inv(head)
    Ht = rt.bone_pose("head", head)
    gain = np.ones_like(out) if rt.fapu_gain is None else rt.fapu_gain
    for i in range(G.shape[0]):
        d = np.zeros(3)
        for p in range(G.indptr[i], G.indptr[i + 1]):
            j = G.indices[p]
            x = Hinv[:3, :3] @ skin[rt.used[j]] + Hinv[:3, 3]
            d += G.data[p] * (rt.frame_transform[j] @ (x - neutral[j]))
        out[i] += gain[i] * d
        out[i] += rt.head_weight[i] * (Ht[:3, :3] @ out[i] + Ht[:3, 3] - out[i])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--target", type=Path, help="mesh to animate (default: see the module docstring)")
    ap.add_argument("--landmarks", type=Path, help="its feature points (with --target)")
    ap.add_argument("--frames", type=int, default=330, help="frames of expressions.fap to time")
    ap.add_argument("--naive-frames", type=int, default=5, help="frames the baseline is timed over")
    args = ap.parse_args(argv)

    from fae.animate.player import Player, playable_head
    from fae.animate.retarget import RetargetPlayer, read_target, retarget
    from fae.commands.common import load_head
    from fae.io.fap import read_fap

    template = load_head(None)[0]
    with tempfile.TemporaryDirectory() as tmp:
        mesh, lm = (args.target, args.landmarks) if args.target else default_target(Path(tmp), template)
        t = time.perf_counter()
        rt = retarget(template, read_target(mesh, lm))
        setup = time.perf_counter() - t
    player = RetargetPlayer(rt, Player(playable_head(template)))
    t = time.perf_counter()
    recorded = [(f.skin_vertices, f.bone_transforms)
                for f in player.player.play(read_fap(REPO / "fap_streams" / "expressions.fap"))][:args.frames]
    physics = len(recorded) / (time.perf_counter() - t)

    player.carry(*recorded[0])  # warm
    t = time.perf_counter()
    for skin, bones in recorded:
        out, _ = player.carry(skin, bones)
    fast = len(recorded) / (time.perf_counter() - t)

    frames = recorded[len(recorded) // 2: len(recorded) // 2 + args.naive_frames]
    t = time.perf_counter()
    for skin, bones in frames:
        slow_out = naive_carry(rt, player._neutral, skin, bones["head"])
    slow = len(frames) / (time.perf_counter() - t)
    check, _ = player.carry(*frames[-1])
    assert np.allclose(check, slow_out, atol=1e-9), f"the baseline disagrees with the transfer by {np.abs(check - slow_out).max()} m"

    print(f"target: {rt.report['target']}  ({rt.vertex_count} vertices, {len(rt.model.skin_vertices)} skin; "
          f"{len(rt.used)} template vertices carried)")
    print(f"set-up (fit + binding, once): {setup:.1f} s")
    print(f"transfer: {fast:.0f} frames/s on one core ({1000 / fast:.2f} ms a frame, {len(recorded)} frames)")
    print(f"baseline, per-vertex Python loop: {slow:.1f} frames/s ({len(frames)} frames)")
    print(f"ratio: {fast / slow:.0f}x")
    print(f"the template's physics for comparison: {physics:.0f} frames/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
