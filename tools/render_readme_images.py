"""Render the README pictures into docs/images/ from the shipped head.

    .venv/bin/python tools/render_readme_images.py [--head templates/generic_head.glb]

Writes (PNG, each well under 300 KB):
  docs/images/template_front.png          the generic head at rest, front view
  docs/images/template_three_quarter.png  the same, three-quarter view
  docs/images/demo_strip.png              a few frames of fap_streams/expressions.fap side by side
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from fae.io.facemodel_gltf import read_facemodel  # noqa: E402
from fae.io.fap import read_fap  # noqa: E402
from fae.render.png import write_png  # noqa: E402
from fae.render.renderer import FaceRenderer  # noqa: E402

MAX_BYTES = 300_000


def demo_frames(model, stream_path: Path, count: int):
    """`count` PlayedFrames spread evenly over the stream (the most expressive moments of each
    expression are in the middle of its segment, so frames are taken at segment centres)."""
    from fae.animate.player import Player

    stream = read_fap(stream_path)
    total = sum(1 for _ in stream)
    wanted = {int((k + 0.5) * total / count) for k in range(count)}
    player = Player(model, device="cpu")
    return [f for f in player.play(stream) if f.index in wanted or len(wanted) == 0][:count]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--head", type=Path, default=REPO / "templates" / "generic_head.glb")
    parser.add_argument("--stream", type=Path, default=REPO / "fap_streams" / "expressions.fap")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    parser.add_argument("--strip-frames", type=int, default=6)
    args = parser.parse_args()
    if not args.head.is_file():
        print(f"{args.head}: head not found (build the template first)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    model = read_facemodel(args.head)
    written = []
    for view, name in (("front", "template_front.png"), ("three-quarter", "template_three_quarter.png")):
        with FaceRenderer(model, size=(480, 480), view=view, supersample=2) as r:
            write_png(args.out / name, r.render(), compress_level=9)
        written.append(args.out / name)
    frames = demo_frames(model, args.stream, args.strip_frames)
    with FaceRenderer(model, size=(240, 240), view="front", supersample=2) as r:
        tiles = [r.render(f.skin_vertices, f.bone_transforms, f.pupil_scale) for f in frames]
    write_png(args.out / "demo_strip.png", np.concatenate(tiles, axis=1), compress_level=9)
    written.append(args.out / "demo_strip.png")
    for path in written:
        size = path.stat().st_size
        print(f"{path.relative_to(REPO) if path.is_relative_to(REPO) else path}: {size / 1000:.0f} KB")
        if size > MAX_BYTES:
            print(f"{path}: larger than {MAX_BYTES // 1000} KB", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
