"""Skin regions of the generic head: every skin vertex in exactly one named region.

Regions keep muscles from acting across the lips and eyelids (paper 000, section 6.1).
Rules read the template's design (millimetres, see template_shapes) and are applied to
|x|, so the partition is mirror-symmetric; `_l` regions lie at x > 0 (the face's left).
"""

from __future__ import annotations

import numpy as np

from fae.anatomy import template_shapes as S

REGION_NAMES = (
    "scalp", "forehead",
    "eyelid_upper_l", "eyelid_upper_r", "eyelid_lower_l", "eyelid_lower_r",
    "nose", "cheek_l", "cheek_r",
    "lip_upper", "lip_lower", "mouth_cavity", "chin", "jaw_l", "jaw_r",
    "ear_l", "ear_r", "neck",
)
LIP_INNER_Z = 86.0  # mm: behind this the slit walls belong to the mouth cavity


def skin_regions(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) int32 index into REGION_NAMES for each skin vertex of the template (V in mm)."""
    idx = {name: i for i, name in enumerate(REGION_NAMES)}
    x, y, z = np.abs(V[:, 0]), V[:, 1], V[:, 2]
    left = V[:, 0] >= 0.0
    out = np.full(len(V), -1, dtype=np.int64)

    def assign(mask, name_l, name_r=None):
        free = (out < 0) & mask
        if name_r is None:
            out[free] = idx[name_l]
        else:
            out[free & left] = idx[name_l]
            out[free & ~left] = idx[name_r]

    cavity = S.mouth_cavity_sdf(V)
    assign((np.abs(cavity) < 1.5) & (z < LIP_INNER_Z), "mouth_cavity")
    assign(S.ear_sdf(V) < 2.0, "ear_l", "ear_r")
    e = S.EYE_CENTER
    d_eye = np.linalg.norm(np.stack([x - e[0], y - e[1], z - e[2]], axis=1), axis=1)
    near_eye = (d_eye < S.EYE_RADIUS + S.EYE_GAP + S.LID_THICKNESS + 3.0) & (np.abs(x - e[0]) < S.FISSURE_HALF_WIDTH + 3.0)
    assign(near_eye & (y >= e[1] + 0.4 * (x - e[0]) / S.FISSURE_HALF_WIDTH), "eyelid_upper_l", "eyelid_upper_r")
    assign(near_eye, "eyelid_lower_l", "eyelid_lower_r")
    y0 = S.STOMION_Y
    mouth = (z > 70.0) & (x < S.MOUTH_HALF_WIDTH + 6.0 - 0.25 * np.clip(y - y0, 0, None))
    assign(mouth & (y > y0) & (y < -56.0) & (S.nose_sdf(V) > 1.0), "lip_upper")
    assign(mouth & (y <= y0) & (y > y0 - 13.0), "lip_lower")
    assign((S.nose_sdf(V) < 1.5) & (y < 12.0) & (y > -58.0) & (x < 22.0), "nose")
    assign((y > 8.0) & (y < 74.0) & (z > 45.0), "forehead")
    assign((y > -75.0) & (y < 8.0) & (z > 30.0), "cheek_l", "cheek_r")
    assign(y > -30.0 + 0.6 * np.clip(-z, 0, None), "scalp")
    assign((y < y0 - 13.0) & (y > -128.0) & (x < 24.0) & (z > 55.0), "chin")
    assign((y > -118.0) & (z > 5.0), "jaw_l", "jaw_r")
    assign(np.ones(len(V), dtype=bool), "neck")
    return out.astype(np.int32)
