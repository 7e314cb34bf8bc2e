"""End-to-end frames/s of `fae play` at 640x480, and where the time goes.

    .venv/bin/python tools/bench_play.py [--frames 100] [--head HEAD.glb]
                                         [--stream fap_streams/expressions.fap]

Measured in one run, on the same frames:
  simulate    the Player alone (FAP frames -> skin positions and bone poses)
  render      FaceRenderer.render_rgba alone (fae's GL program, per-vertex Blinn-Phong)
  pyrender    the baseline: pyrender's own scene renderer (its physically based shader)
              drawing the same geometry as one primitive updated in place, with its
              OSMesa shader-cache leak and numpy-2 problems patched so that it can run
              (the way fae rendered before)
  encode      VideoWriter alone (H.264 in ffmpeg's process)
  serial      the whole pipeline in one thread (render_video(overlap=False))
  overlapped  the whole pipeline with the Player in a producer thread (what `fae play` runs)
and prints frames/s and the ratios render/pyrender and overlapped/serial.

Head: --head, else the shipped head (fae/data/generic_head.glb) (a head without a baked fap_mapping is
calibrated first, which takes minutes); the synthetic test head with generated jaw frames
when the Player or the head is missing.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from fae.data import shipped_head_path  # noqa: E402


def load_head_and_frames(head: Path, stream_path: Path, n: int):
    """(model, label, frame source factory) for the benchmark."""
    try:
        from fae.animate.player import Player, playable_head
    except ImportError:
        Player = None
    if head.is_file() and Player is not None:
        from fae.io.facemodel_gltf import read_facemodel
        from fae.io.fap import read_fap

        model = read_facemodel(head)
        t = time.perf_counter()
        player = Player(playable_head(model, device="cpu"))
        note = "" if model.fap_mapping else f" (calibrated on load, {time.perf_counter() - t:.0f} s)"

        def source():
            player.reset()
            for i, f in enumerate(player.play(read_fap(stream_path))):
                if i >= n:
                    return
                yield f

        return model, f"{head.name}{note} + Player on {stream_path.name}", source
    sys.path.insert(0, str(REPO / "tests"))
    from test_render_support import jaw_frames, synthetic_head

    model = synthetic_head()
    angles = 0.3 * np.sin(np.linspace(0, 4 * np.pi, n)) ** 2
    return model, "synthetic head + generated jaw frames (no Player or head)", lambda: jaw_frames(model, angles)


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


class PyrenderBaseline:
    """The same triangles, colours and camera through pyrender's Renderer (PBR shader)."""

    def __init__(self, renderer, size):
        import OpenGL.contextdata
        import pyrender
        from pyrender.shader_program import ShaderProgramCache

        if not hasattr(np, "infty"):
            np.infty = np.inf  # pyrender 0.1.45's Mesh.bounds predates numpy 2
        if not getattr(ShaderProgramCache, "_keyed_by_address", False):
            # Its cache is keyed on a ctypes pointer OSMesa returns anew on every call: it
            # would recompile (and leak ~3 MB) every frame. Key it on the address instead.
            original = ShaderProgramCache.get_program

            def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
                ctx = OpenGL.contextdata.getContext()
                key = (ctypes.cast(ctx, ctypes.c_void_p).value, vertex_shader, fragment_shader, geometry_shader,
                       tuple(sorted((defines or {}).items())))
                programs = self.__dict__.setdefault("_by_address", {})
                if key not in programs:
                    programs[key] = original(self, vertex_shader, fragment_shader, geometry_shader, defines)
                return programs[key]

            ShaderProgramCache.get_program = get_program
            ShaderProgramCache._keyed_by_address = True
        from fae.render.renderer import LIGHTS, _make_platform

        self.fae = renderer
        self.size = size
        P, N = renderer.frame_geometry()
        from OpenGL import GL

        self.GL = GL
        rgba = np.concatenate([renderer.vertex_colors, np.ones((len(P), 1), np.float32)], axis=1)
        material = pyrender.MetallicRoughnessMaterial(baseColorFactor=np.ones(4), metallicFactor=0.0,
                                                      roughnessFactor=0.6, doubleSided=True)
        self.primitive = pyrender.Primitive(positions=P, normals=N, color_0=rgba,
                                            indices=renderer.triangles, material=material)
        self.scene = pyrender.Scene(bg_color=np.array([0.8, 0.82, 0.85, 1.0]), ambient_light=np.full(3, 0.22))
        cam = renderer.camera
        self.scene.add(pyrender.PerspectiveCamera(yfov=cam.yfov, znear=cam.znear, zfar=cam.zfar,
                                                  aspectRatio=size[0] / size[1]), pose=cam.pose)
        for direction, color, intensity in LIGHTS:
            z = cam.pose[:3, :3] @ (np.asarray(direction) / np.linalg.norm(direction))
            x = np.cross((0.0, 1.0, 0.0), z)
            x /= np.linalg.norm(x)
            pose = np.eye(4)
            pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, np.cross(z, x), z
            self.scene.add(pyrender.DirectionalLight(color=np.asarray(color), intensity=np.pi * intensity), pose=pose)
        self.scene.add(pyrender.Mesh([self.primitive]))
        self.platform = _make_platform(*size)
        self.renderer = pyrender.Renderer(*size)
        self.renderer.render(self.scene, pyrender.RenderFlags.NONE)
        self.staging = np.empty((len(P), 10), dtype=np.float32)
        self.staging[:, 6:] = rgba
        self.flags = pyrender.RenderFlags.NONE

    def render(self, skin, bones, pupils) -> np.ndarray:
        P, N = self.fae.frame_geometry(skin, bones, pupils)
        self.staging[:, :3], self.staging[:, 3:6] = P, N
        self.platform.make_current()
        GL = self.GL
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self.primitive._buffers[0])
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, self.staging.nbytes, self.staging)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        self.renderer.render(self.scene, self.flags)
        return self.renderer.read_color_buf()

    def close(self) -> None:
        self.platform.make_current()
        self.renderer.delete()
        self.platform.delete_context()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--baseline-frames", type=int, default=40)
    parser.add_argument("--head", type=Path, default=shipped_head_path())
    parser.add_argument("--stream", type=Path, default=REPO / "fap_streams" / "expressions.fap")
    parser.add_argument("--size", default="640x480")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))

    from fae.render.play import _snapshot, render_video
    from fae.render.renderer import FaceRenderer
    from fae.render.video import VideoWriter

    model, label, source = load_head_and_frames(args.head, args.stream, args.frames)
    print(f"head/frames: {label}; {model.skin_vertex_count} skin vertices, {len(model.skin_faces)} triangles; "
          f"{size[0]}x{size[1]}; {os.cpu_count()} cores, LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS')}")
    list(source())  # warm-up: Warp kernels compiled/loaded, caches filled
    frames = []
    sim_s = timed(lambda: frames.extend(_snapshot(f) for f in source()))
    n = len(frames)
    results = {"simulate": sim_s}
    with FaceRenderer(model, size=size) as r, tempfile.TemporaryDirectory() as tmp:
        for f in frames[:3]:
            r.render_rgba(*f)
        images = []
        results["render"] = timed(lambda: images.extend(r.render_rgba(*f) for f in frames))
        k = min(args.baseline_frames, n)
        baseline = PyrenderBaseline(r, size)
        try:
            results["pyrender"] = timed(lambda: [baseline.render(*f) for f in frames[:k]]) * n / k
        finally:
            baseline.close()

        def encode():
            with VideoWriter(Path(tmp) / "encode.mp4", size, 25, channels=4) as v:
                for im in images:
                    v.write(im)

        results["encode"] = timed(encode)
        # Pipelines alternate so that load from other processes hits both alike.
        serial, overlapped, cpu = [], [], []
        for _ in range(2):
            serial.append(render_video(source(), r, Path(tmp) / "s.mp4", 25, overlap=False))
            before = os.times()
            overlapped.append(render_video(source(), r, Path(tmp) / "o.mp4", 25, overlap=True))
            after = os.times()
            cpu.append(sum(after[:4]) - sum(before[:4]))  # this process and ffmpeg, user + system
    results["serial"] = min(t.wall for t in serial)
    results["overlapped"] = min(t.wall for t in overlapped)
    best = min(overlapped, key=lambda t: t.wall)
    print(f"{'stage':<14}{'frames/s':>10}{'ms/frame':>10}")
    for name, seconds in results.items():
        print(f"{name:<14}{n / seconds:>10.1f}{1e3 * seconds / n:>10.1f}")
    print(f"overlapped run split: simulate {1e3 * best.simulate / n:.1f} ms/frame (producer thread), "
          f"render {1e3 * best.render / n:.1f}, encode hand-off {1e3 * best.encode / n:.1f}")
    print(f"ratio render / pyrender:     {results['pyrender'] / results['render']:.2f}x faster")
    print(f"ratio overlapped / serial:   {results['serial'] / results['overlapped']:.2f}x faster")
    print(f"end to end: {n / results['overlapped']:.1f} frames/s (target 25)")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    per_frame = min(cpu) / n
    print(f"CPU time of the overlapped run (fae + ffmpeg): {1e3 * per_frame:.1f} ms/frame; with {cores} idle "
          f"cores and perfect overlap at most {cores / per_frame:.1f} frames/s (load from other processes "
          f"stretches wall time, not CPU time)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
