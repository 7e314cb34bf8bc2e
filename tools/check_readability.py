"""Do renders follow the FAPs? A face-landmark model looks at the face as a person would.

    .venv/bin/python tools/check_readability.py [--head HEAD.glb] [--steps 6]

For each FAP (alone, settled, at `--steps` values from 0 to its upper limit), the head is
drawn from the front and MediaPipe Face Mesh (the optional `fae[landmarks]` dependency,
weights inside its wheel) finds its points; a measure a person would read off the picture
is taken, in units of the eye distance:

- lip corner raise (FAPs 12, 13, 59, 60): how high the corner sits above its rest place;
- eyelid closing (19, 20): how far the lid gap has closed (upper to lower lid);
- jaw (3) and lip stretch (6, 7), for comparison: the lip gap, how far the corner has moved
  out. (Not the brows: the shipped head has no brow hair, and the landmark model places the
  brows of a hairless face from the eyes; its brow points do not follow brow FAPs.)

Prints, per FAP, Pearson's r between the FAP value and the measure (1: the picture follows
the value exactly) and the measure's range. Exit 1 when any r is below --min-r (0.8).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

# MediaPipe Face Mesh indices (subject's left is the image's right)
EYE_OUTER = (33, 263)
MOUTH_CORNER = {"r": 61, "l": 291}
LID = {"l": (386, 374), "r": (159, 145)}  # upper, lower
INNER_LIPS = (13, 14)

# FAP -> (what, side, sign of the image-y measure)
CHECKS = {
    12: ("corner raise", "l"), 13: ("corner raise", "r"), 59: ("corner raise", "l"), 60: ("corner raise", "r"),
    19: ("lid closing", "l"), 20: ("lid closing", "r"),
    3: ("lip gap", ""), 6: ("corner out", "l"), 7: ("corner out", "r"),
}


def measure(points: np.ndarray, rest: np.ndarray, what: str, side: str) -> float:
    """The measure of `what` on MediaPipe points (468, 2) pixels against the rest face's,
    in eye distances (image y grows downwards)."""
    eye = np.linalg.norm(rest[EYE_OUTER[0]] - rest[EYE_OUTER[1]])
    if what == "corner raise":
        k = MOUTH_CORNER[side]
        return float(rest[k, 1] - points[k, 1]) / eye
    if what == "lid closing":
        up, low = LID[side]
        return float((rest[low, 1] - rest[up, 1]) - (points[low, 1] - points[up, 1])) / eye
    if what == "lip gap":
        return float(points[INNER_LIPS[1], 1] - points[INNER_LIPS[0], 1]) / eye
    if what == "corner out":
        k = MOUTH_CORNER[side]
        centre = 0.5 * (rest[MOUTH_CORNER["l"], 0] + rest[MOUTH_CORNER["r"], 0])
        return float(abs(points[k, 0] - centre) - abs(rest[k, 0] - centre)) / eye
    raise ValueError(what)


def readability(face, faps=None, steps: int = 6, size: int = 640) -> dict[int, dict]:
    """Per FAP: {"what", "values", "measures", "r"} (see module docstring)."""
    from fae.mpeg4.faptables import FAP_LIMITS
    from fae.animate.player import Player, playable_head
    from fae.render.landmarks import detect_pixels
    from fae.render.renderer import FaceRenderer

    player = Player(playable_head(face))
    out = {}
    with FaceRenderer(player.face, size=(size, size), view="front") as renderer:
        def points_at(values: np.ndarray) -> np.ndarray | None:
            player.reset()
            for _ in range(40):
                skin = player.step(values, dt=0.04)
            image = np.asarray(renderer.render(skin, player.bone_transforms, player.pupil_scale))[..., :3]
            return detect_pixels(np.ascontiguousarray(image))

        rest = points_at(np.zeros(68))
        if rest is None:
            raise RuntimeError("the landmark model finds no face on the rest pose")
        for k in faps or CHECKS:
            what, side = CHECKS[k]
            values = np.linspace(0.0, FAP_LIMITS[k - 1, 1], steps)
            got = []
            for v in values:
                frame = np.zeros(68)
                frame[k - 1] = v
                pts = points_at(frame)
                got.append(np.nan if pts is None else measure(pts, rest, what, side))
            got = np.array(got)
            ok = np.isfinite(got)
            r = float(np.corrcoef(values[ok], got[ok])[0, 1]) if ok.sum() > 2 and np.ptp(got[ok]) > 0 else float("nan")
            out[k] = {"what": what, "values": values.tolist(), "measures": got.tolist(), "r": r}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--head", default=None, help="FaceModel .glb (default: the shipped head)")
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--min-r", type=float, default=0.8)
    args = ap.parse_args(argv)

    from fae.mpeg4.faptables import FAP_NAME
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel

    report = readability(read_facemodel(args.head or shipped_head_path()), steps=args.steps)
    worst = 1.0
    for k, r in report.items():
        m = np.array(r["measures"])
        print(f"FAP {k:>2} {FAP_NAME[k - 1]:<22} {r['what']:<13} r = {r['r']:.3f}   "
              f"measure {np.nanmin(m):+.3f} .. {np.nanmax(m):+.3f} eye distances")
        worst = min(worst, r["r"] if np.isfinite(r["r"]) else -1.0)
    return 0 if worst >= args.min_r else 1


if __name__ == "__main__":
    sys.exit(main())
