"""End-to-end frames/s of `fae play` at 640x480, and where the time goes.

    .venv/bin/python tools/bench_play.py [--frames 100] [--stream fap_streams/expressions.fap]

Measured in one run, on the same frames:
  simulate   the Player alone (FAP frames -> skin positions and bone poses)
  render     FaceRenderer alone (in-place vertex-buffer updates, shader cache fixed)
  naive      the baseline a plain pyrender user gets: pyrender's own shader-cache lookup
             (recompiles every frame under OSMesa), a new skin Mesh every frame, depth
             read back with colour
  encode     VideoWriter alone (H.264 in ffmpeg's process)
  serial     the whole pipeline in one thread (render_video(overlap=False))
  overlapped the whole pipeline with the Player in a producer thread (what `fae play` runs)
and prints frames/s and the ratios render/naive and overlapped/serial.

Head: templates/generic_head.glb when it exists, else the synthetic test head (and jaw
frames instead of the Player when fae.animate.player or the template is missing).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def load_head_and_frames(stream_path: Path, n: int):
    """(model, label, frame source factory) for the benchmark."""
    template = REPO / "templates" / "generic_head.glb"
    try:
        from fae.animate.player import Player
    except ImportError:
        Player = None
    if template.is_file() and Player is not None:
        from fae.io.facemodel_gltf import read_facemodel
        from fae.io.fap import read_fap

        model = read_facemodel(template)
        player = Player(model, device="cpu")

        def source():
            player.reset()
            for i, f in enumerate(player.play(read_fap(stream_path))):
                if i >= n:
                    return
                yield f

        return model, f"{template.name} + Player on {stream_path.name}", source
    sys.path.insert(0, str(REPO / "tests"))
    from test_render_support import jaw_frames, synthetic_head

    model = synthetic_head()
    angles = 0.3 * np.sin(np.linspace(0, 4 * np.pi, n)) ** 2
    return model, "synthetic head + generated jaw frames (no Player/template yet)", lambda: jaw_frames(model, angles)


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def naive_render_seconds(model, frames, size) -> float:
    """Baseline: pyrender's own shader lookup, a new skin Mesh per frame, depth readback."""
    import pyrender
    from pyrender.shader_program import ShaderProgramCache

    from fae.render.renderer import FaceRenderer

    patched = ShaderProgramCache.get_program
    ShaderProgramCache.get_program = ShaderProgramCache.unpatched_get_program
    try:
        with FaceRenderer(model, size=size) as r:
            scene = r._scene
            node = next(iter(scene.get_nodes(name="head")))
            template = r._primitive

            def run():
                nonlocal node
                for f in frames:
                    r._platform.make_current()
                    scene.remove_node(node)
                    P, Q = r.frame_geometry(*f)
                    prim = pyrender.Primitive(positions=P, normals=Q, color_0=template.color_0,
                                              indices=template.indices, material=template.material)
                    node = scene.add(pyrender.Mesh([prim]), name="head")
                    r._renderer.render(scene, r._flags)
                    r._renderer.read_color_buf()
                    r._renderer.read_depth_buf()

            return timed(run)
    finally:
        ShaderProgramCache.get_program = patched


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--naive-frames", type=int, default=30, help="the baseline leaks ~3 MB/frame: keep it short")
    parser.add_argument("--stream", type=Path, default=REPO / "fap_streams" / "expressions.fap")
    parser.add_argument("--size", default="640x480")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))

    from fae.render.play import _snapshot, render_video
    from fae.render.renderer import FaceRenderer
    from fae.render.video import VideoWriter

    model, label, source = load_head_and_frames(args.stream, args.frames)
    print(f"head/frames: {label}; {model.skin_vertex_count} skin vertices, {len(model.skin_faces)} triangles; "
          f"{size[0]}x{size[1]}")
    list(source())  # warm-up: Warp kernels compiled/loaded, caches filled
    frames = []
    sim_s = timed(lambda: frames.extend(_snapshot(f) for f in source()))
    n = len(frames)
    results = {"simulate": sim_s}
    with FaceRenderer(model, size=size) as r, tempfile.TemporaryDirectory() as tmp:
        for f in frames[:3]:
            r.render(*f)
        images = []
        results["render"] = timed(lambda: images.extend(r.render(*f) for f in frames))

        def encode():
            with VideoWriter(Path(tmp) / "encode.mp4", size, 25) as v:
                for im in images:
                    v.write(im)

        results["encode"] = timed(encode)
        # Pipelines alternate so that load from other processes hits both alike.
        serial, overlapped = [], []
        for _ in range(2):
            serial.append(render_video(source(), r, Path(tmp) / "s.mp4", 25, overlap=False))
            overlapped.append(render_video(source(), r, Path(tmp) / "o.mp4", 25, overlap=True))
    k = min(args.naive_frames, n)
    naive_s = naive_render_seconds(model, frames[:k], size) * n / k
    results["naive render"] = naive_s
    results["serial"] = min(t.wall for t in serial)
    results["overlapped"] = min(t.wall for t in overlapped)
    best = min(overlapped, key=lambda t: t.wall)
    print(f"{'stage':<14}{'frames/s':>10}{'ms/frame':>10}")
    for name, seconds in results.items():
        print(f"{name:<14}{n / seconds:>10.1f}{1e3 * seconds / n:>10.1f}")
    print(f"overlapped run split: simulate {1e3 * best.simulate / n:.1f} ms/frame (producer thread), "
          f"render {1e3 * best.render / n:.1f}, encode hand-off {1e3 * best.encode / n:.1f}")
    print(f"ratio render / naive render: {naive_s / results['render']:.2f}x faster")
    print(f"ratio overlapped / serial:   {results['serial'] / results['overlapped']:.2f}x faster")
    print(f"end to end: {n / results['overlapped']:.1f} frames/s (target 25)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
