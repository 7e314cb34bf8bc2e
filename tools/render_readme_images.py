"""Render the README pictures into docs/images/ from the shipped head.

    .venv/bin/python tools/render_readme_images.py [--head HEAD.glb]

Writes (PNG, each well under 300 KB):
  docs/images/template_front.png          the generic head at rest, front view
  docs/images/template_three_quarter.png  the same, three-quarter view
  docs/images/demo_strip.png              a few frames of fap_streams/expressions.fap side by side
  docs/images/adapt_bust.png              `fae adapt --compare` on a bust the project makes
                                          (fae.adapt.synthetic.bust_scan): scan, head, both
  docs/images/photo_head.png              the head `fae adapt --photo` makes of scikit-image's
                                          astronaut portrait: as the photo saw it, three-quarter,
                                          profile, and two moments of expressions.fap

--only NAME renders one of them (template, strip, adapt, photo).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from fae.data import shipped_head_path  # noqa: E402
from fae.io.facemodel_gltf import read_facemodel  # noqa: E402
from fae.io.fap import read_fap  # noqa: E402
from fae.render.png import write_png  # noqa: E402
from fae.render.renderer import FaceRenderer  # noqa: E402

MAX_BYTES = 300_000


def demo_frames(model, stream_path: Path, count: int):
    """`count` PlayedFrames spread evenly over the stream (the most expressive moments of each
    expression are in the middle of its segment, so frames are taken at segment centres)."""
    from fae.animate.player import Player, playable_head

    stream = read_fap(stream_path)
    total = sum(1 for _ in stream)
    wanted = {int((k + 0.5) * total / count) for k in range(count)}
    player = Player(playable_head(model, device="cpu"))
    return [f for f in player.play(stream) if f.index in wanted or len(wanted) == 0][:count]


def adapt_picture(model) -> np.ndarray:
    """The comparison picture of `fae adapt` on the synthetic bust (seed 3)."""
    from fae.adapt.calibration import apply_transform
    from fae.adapt.from_scan import adapt_to_scan
    from fae.adapt.head_pose import find_head, kept_part
    from fae.adapt.synthetic import template_bust
    from fae.adapt.transfer import visible_skin
    from fae.render.compare import comparison_image
    from fae.render.framing import camera_view
    from fae.render.landmarks import landmark_pairs

    bust = template_bust(model)
    head = find_head(model, bust.vertices, bust.faces)
    part = kept_part(apply_transform(head.transform, bust.vertices), bust.faces, head.keep)
    found = landmark_pairs(model, *part, camera_view(model, "front", aspect=1.0), seen=visible_skin(model))
    adapted, _ = adapt_to_scan(model, bust.vertices, bust.faces, head, (found.face, found.bary, found.scan_points))
    return comparison_image(adapted, bust.vertices, bust.faces, head.keep, size=(300, 300))


def photo_picture(model, stream_path: Path) -> np.ndarray:
    """The head of skimage's astronaut photo (fae adapt --photo, calibrated from the
    template's mapping): through the photo's camera, three-quarter, profile, then joy and
    surprise from the expressions stream."""
    from skimage import data

    from fae.animate.calibrate import calibrate
    from fae.commands.adapt import photo_head
    from fae.render.compare import photo_comparison_image

    head, report = photo_head(model, data.astronaut(), "astronaut")
    if report["verdict"]:
        raise SystemExit(f"the photo's head is not to be trusted: {report['verdict']}")
    head = calibrate(head, start=model.fap_mapping)
    size = 300
    seen = photo_comparison_image(head, data.astronaut(), height=size)[:, size:2 * size]  # the head as the photo saw it
    tiles = [seen]
    for view in ("three-quarter", "profile"):
        with FaceRenderer(head, size=(size, size), view=view, supersample=2) as r:
            tiles.append(r.render())
    frames = demo_frames(head, stream_path, 6)
    with FaceRenderer(head, size=(size, size), view="front", supersample=2) as r:
        tiles += [r.render(f.skin_vertices, f.bone_transforms, f.pupil_scale) for f in (frames[0], frames[5])]
    return np.concatenate(tiles, axis=1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--head", type=Path, default=shipped_head_path())
    parser.add_argument("--stream", type=Path, default=REPO / "fap_streams" / "expressions.fap")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    parser.add_argument("--strip-frames", type=int, default=6)
    parser.add_argument("--only", choices=("template", "strip", "adapt", "photo"))
    args = parser.parse_args()
    if not args.head.is_file():
        print(f"{args.head}: head not found (build the template first)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    model = read_facemodel(args.head)
    written = []
    if args.only in (None, "template"):
        for view, name in (("front", "template_front.png"), ("three-quarter", "template_three_quarter.png")):
            with FaceRenderer(model, size=(480, 480), view=view, supersample=2) as r:
                write_png(args.out / name, r.render(), compress_level=9)
            written.append(args.out / name)
    if args.only in (None, "strip"):
        frames = demo_frames(model, args.stream, args.strip_frames)
        with FaceRenderer(model, size=(240, 240), view="front", supersample=2) as r:
            tiles = [r.render(f.skin_vertices, f.bone_transforms, f.pupil_scale) for f in frames]
        write_png(args.out / "demo_strip.png", np.concatenate(tiles, axis=1), compress_level=9)
        written.append(args.out / "demo_strip.png")
    if args.only in (None, "adapt"):
        write_png(args.out / "adapt_bust.png", adapt_picture(model), compress_level=9)
        written.append(args.out / "adapt_bust.png")
    if args.only in (None, "photo"):
        write_png(args.out / "photo_head.png", photo_picture(model, args.stream), compress_level=9)
        written.append(args.out / "photo_head.png")
    for path in written:
        size = path.stat().st_size
        print(f"{path.relative_to(REPO) if path.is_relative_to(REPO) else path}: {size / 1000:.0f} KB")
        if size > MAX_BYTES:
            print(f"{path}: larger than {MAX_BYTES // 1000} KB", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
