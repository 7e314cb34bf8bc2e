"""Muscles of the generic head: Waters-style linear muscles and three sphincters.

Each linear muscle is attached on bone (cranium or mandible) and inserted in the skin;
both ends are stored as surface points so they follow any adaptation of the head. The
layout (millimetres, the template's frame) follows the anatomy atlases: origins on the
frontal bone, maxilla, zygoma and mandible, insertions in the brow, the lips and the
modiolus at the mouth corner.

Regions: a muscle that inserts in one lip moves only that lip (plus the skin it crosses);
the muscles of the modiolus (zygomaticus major, risorius, depressor anguli oris,
buccinator) move both lips, with zones that fade out within about 15 mm of the corner,
so they pull the corner without dragging the far lip. Muscles never reach the mouth
cavity, the other side's regions, the ears, scalp or neck.
"""

from __future__ import annotations

import numpy as np

from fae.anatomy import template_shapes as S
from fae.anatomy.surface_points import closest_point, vertex_point
from fae.io.facemodel import Muscle

MM = 1e-3

# name: (bone, attachment target mm, insertion target mm, zone half-angle deg, regions (l side))
_LINEAR = {
    "frontalis_inner": ("cranium", (16.0, 68.0, 76.0), (16.0, 31.0, 93.0), 22.0, ["forehead"]),
    "frontalis_outer": ("cranium", (34.0, 64.0, 70.0), (36.0, 31.0, 86.0), 22.0, ["forehead"]),
    "corrugator": ("cranium", (6.0, 10.0, 86.0), (24.0, 22.0, 92.0), 25.0, ["forehead", "eyelid_upper"]),
    "levator_labii_superioris": ("cranium", (22.0, -20.0, 82.0), (12.0, -68.0, 97.0), 20.0, ["cheek", "lip_upper", "nose"]),
    "levator_labii_superioris_alaeque_nasi": ("cranium", (9.0, -2.0, 88.0), (9.0, -60.0, 100.0), 18.0, ["nose", "lip_upper", "cheek"]),
    "zygomaticus_major": ("cranium", (54.0, -22.0, 48.0), (26.0, -77.0, 86.0), 20.0, ["cheek", "lip_upper", "lip_lower", "jaw"]),
    "zygomaticus_minor": ("cranium", (44.0, -16.0, 66.0), (17.0, -70.0, 95.0), 18.0, ["cheek", "lip_upper"]),
    "risorius": ("mandible", (46.0, -70.0, 24.0), (26.0, -78.0, 86.0), 18.0, ["cheek", "jaw", "lip_upper", "lip_lower"]),
    "depressor_anguli_oris": ("mandible", (30.0, -110.0, 56.0), (25.0, -80.0, 87.0), 20.0, ["jaw", "chin", "lip_lower", "lip_upper"]),
    "depressor_labii_inferioris": ("mandible", (16.0, -110.0, 72.0), (10.0, -87.0, 95.0), 20.0, ["chin", "lip_lower"]),
    "mentalis": ("mandible", (6.0, -98.0, 80.0), (6.0, -108.0, 92.0), 25.0, ["chin", "lip_lower"]),
    "buccinator": ("mandible", (40.0, -80.0, 38.0), (27.0, -78.0, 84.0), 20.0, ["cheek", "jaw", "lip_upper", "lip_lower"]),
}
_SIDED = {"eyelid_upper", "eyelid_lower", "cheek", "jaw"}


def _sided(regions: list[str], side: str) -> list[str]:
    return [f"{r}_{side}" if r in _SIDED else r for r in regions]


def template_muscles(V: np.ndarray, F: np.ndarray, region: np.ndarray, parts_mm: dict) -> list[Muscle]:
    """The template's muscles (positions from the skin `V (n, 3)` mm, faces F, and the parts in mm)."""

    muscles: list[Muscle] = []
    flip = np.array([-1.0, 1.0, 1.0])
    for name, (bone, att, ins, angle, regions) in _LINEAR.items():
        BV, BF = parts_mm[bone]
        for side, sign in (("l", np.ones(3)), ("r", flip)):
            a = closest_point(bone, BV, BF, np.asarray(att) * sign)
            i = closest_point("skin", V, F, np.asarray(ins) * sign)
            pa = np.asarray(a.bary) @ BV[BF[a.triangle]]
            pi = np.asarray(i.bary) @ V[F[i.triangle]]
            length = float(np.linalg.norm(pi - pa)) * MM
            muscles.append(Muscle(
                name=f"{name}_{side}", kind="linear", attachment=a, insertion=i,
                regions=_sided(regions, side), zone_angle=float(np.radians(angle)),
                fall_start=0.75 * length, fall_end=1.25 * length))
    # sphincters: centre on the skin, ellipse in the face's x/y directions
    axes = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    mid = np.flatnonzero(V[:, 0] == 0.0)
    lips = mid[np.abs(V[mid, 1] - S.STOMION_Y) < 2.0]
    centre = int(lips[np.argmax(V[lips, 2])])
    muscles.append(Muscle(
        name="orbicularis_oris", kind="sphincter", attachment=vertex_point("skin", F, centre), insertion=None,
        regions=["lip_upper", "lip_lower"], semi_axes=np.array([31.0, 17.0]) * MM, axes=axes.copy()))
    e = S.EYE_CENTER
    for side, sign in (("l", np.ones(3)), ("r", flip)):
        target = (e + np.array([0.0, 0.0, S.EYE_RADIUS + S.EYE_GAP])) * sign
        muscles.append(Muscle(
            name=f"orbicularis_oculi_{side}", kind="sphincter", attachment=closest_point("skin", V, F, target),
            insertion=None, regions=[f"eyelid_upper_{side}", f"eyelid_lower_{side}", f"cheek_{side}", "forehead"],
            semi_axes=np.array([27.0, 21.0]) * MM, axes=axes.copy()))
    return muscles
