"""A head's skin cut by a plane across the face (x = const): at rest and posed, side by side.

The profile of the cut (y up, z towards the viewer, millimetres) shows what a render from the
front hides and a fold count only counts: a lip's inner wall tilting into view as its margin
rises, a lid's front buckling over the eyeball, a bevel at a rim turning over. Segments of
triangles `fae verify-skin` calls folded or creased in the posed frame are red, the mouth's
lining grey. The posed frame is a stream's frame, or FAP values held until the skin settles.

    .venv/bin/python tools/section_view.py [HEAD.glb] --stream S.fap --frame 41 --x 0.5 -o cut.png
    .venv/bin/python tools/section_view.py [HEAD.glb] --faps 4:-190,8:-190,9:-190 --x 0.5 -o cut.png
    (--center FDP and --half MM frame the plot: default about 8.2, the lower lip's middle, 20 mm)
"""

from __future__ import annotations

import argparse

import numpy as np

from fae.animate.player import Player, playable_head
from fae.animate.skin_check import SkinCheck, in_head_frame
from fae.data import shipped_head_path
from fae.io.fap import read_fap
from fae.io.facemodel_gltf import read_facemodel
from fae.mpeg4.faps import FAP_COUNT

SETTLE_FRAMES = 30  # held FAP values: ramped over 10 frames, then held


def held_values(spec: str) -> np.ndarray:
    """(68,) FAP values from "k:v,k:v" (FAP numbers, FAPU units)."""
    values = np.zeros(FAP_COUNT)
    for item in filter(None, spec.split(",")):
        k, v = item.split(":")
        values[int(k) - 1] = float(v)
    return values


def section_segments(V: np.ndarray, F: np.ndarray, cut_by: np.ndarray, x: float) -> list[tuple[int, np.ndarray]]:
    """(triangle, (2, 3) segment of it on V) for the triangles of F (m, 3) that the plane x
    (metres) crosses on cut_by (n, 3): the same triangles cut on the rest and posed skin."""
    s = cut_by[F][:, :, 0] - x
    out = []
    for t in np.flatnonzero((s.min(axis=1) < 0) & (s.max(axis=1) > 0)):
        ends = []
        for a, b in ((0, 1), (1, 2), (2, 0)):
            if (s[t, a] < 0) != (s[t, b] < 0):
                w = s[t, a] / (s[t, a] - s[t, b])
                ends.append(V[F[t, a]] * (1 - w) + V[F[t, b]] * w)
        if len(ends) == 2:
            out.append((int(t), np.array(ends)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("head", nargs="?", default=None, help="FaceModel .glb (default: the shipped head)")
    ap.add_argument("--stream", help=".fap stream; its --frame is shown")
    ap.add_argument("--frame", type=int, default=0)
    ap.add_argument("--faps", help='FAP values held instead, "k:v,k:v"')
    ap.add_argument("--x", type=float, default=0.0, help="the cutting plane, mm across the face (+x: its left)")
    ap.add_argument("--center", default="8.2", help="feature point the plot is centred on")
    ap.add_argument("--half", type=float, default=20.0, help="half the plot's size, mm")
    ap.add_argument("-o", "--output", required=True, help="PNG")
    args = ap.parse_args()
    if (args.stream is None) == (args.faps is None):
        ap.error("give --stream (with --frame) or --faps")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    face = read_facemodel(args.head or shipped_head_path())
    player = Player(playable_head(face))
    if args.faps is not None:
        values = held_values(args.faps)
        frames = [values * min(1.0, (i + 1) / 10.0) for i in range(SETTLE_FRAMES)]
        title = f"FAPs {args.faps} held"
    else:
        frames = read_fap(args.stream)
        title = f"frame {args.frame}"
    posed = None
    for frame in player.play(frames):
        posed = frame
        if args.faps is None and frame.index == args.frame:
            break
    skin = in_head_frame(posed.skin_vertices, posed.bone_transforms["head"])
    folded = SkinCheck(face).frame(skin).folded
    rest = np.asarray(face.skin_vertices, dtype=np.float64)
    F = np.asarray(face.skin_faces)
    names, region = list(face.region_names), np.asarray(face.skin_region)
    lining = (region[F] == names.index("mouth_cavity")).any(axis=1) if "mouth_cavity" in names \
        else np.zeros(len(F), dtype=bool)
    centre = face.feature_point_positions()[args.center] * 1e3
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    for ax, V, name in ((axes[0], rest, "rest"), (axes[1], skin, title)):
        for t, seg in section_segments(V, F, rest, args.x / 1e3):
            colour = "red" if folded[t] else ("0.65" if lining[t] else "black")
            ax.plot(seg[:, 2] * 1e3, seg[:, 1] * 1e3, color=colour, lw=1.4)
        ax.set_title(f"{name}, x = {args.x:g} mm")
        ax.set_xlim(centre[2] - args.half, centre[2] + args.half)
        ax.set_ylim(centre[1] - args.half, centre[1] + args.half)
        ax.set_aspect("equal")
        ax.set_xlabel("z, mm (towards the viewer)")
        ax.set_ylabel("y, mm")
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.output, dpi=80)
    print(f"{args.output}: {int(folded.sum())} triangles folded or creased in the posed frame")


if __name__ == "__main__":
    main()
