"""Per-FAP arrays the runtime needs, from the standard's table (fae.mpeg4), plus the FAPU of a head.

Ranges the runtime clamps to (`FAP_LIMITS`, FAPU units; FAP number-1 indexed):
- translations: the I range taken as FAPU units (open_jaw +-1080 MNS is about 3 cm on an
  adult face, the largest the anatomy allows); the standard's coder range times the
  quantiser step (`FapInfo.value_range`, e.g. +-4320 MNS = 13 cm for open_jaw) bounds
  what a bitstream can carry, not what a face can do; unidirectional FAPs (open_jaw,
  thrust_jaw, lift_*_cheek) are clamped at 0 below;
- rotations (eyeballs, head, tongue roll): `FapInfo.value_range` (rigid, any angle is
  stable);
- pupils: the I range.
"Half its range" (verify-faps) is half the positive translation limit.
"""

from __future__ import annotations

import numpy as np

from fae.mpeg4.faps import AU, FAP_COUNT, FAPS
from fae.mpeg4.fapu import fapu0_from_positions, fapu_from_fapu0

FAP_DIRECTION = np.array([info.direction or (0.0, 0.0, 0.0) for info in FAPS], dtype=np.float64)  # (68, 3)
FAP_UNIT_NAME = [info.fapu for info in FAPS]
FAP_FEATURE_POINT = [info.feature_point for info in FAPS]
FAP_NAME = [info.name for info in FAPS]


def _limits() -> np.ndarray:
    out = np.zeros((FAP_COUNT, 2))
    for info in FAPS:
        if info.number <= 2:
            continue
        if info.is_rotation:
            lo, hi = info.value_range
        else:
            lo, hi = float(info.i_range[0]), float(info.i_range[1])
        if info.bidirectional is False:
            lo = max(lo, 0.0)
        out[info.number - 1] = (lo, hi)
    return out


FAP_LIMITS = _limits()  # (68, 2) FAPU units

# Low-level FAPs whose motion is a feature point's translation on the skin (verify-faps' set).
SKIN_TRANSLATION_FAPS = tuple(
    info.number for info in FAPS
    if info.number >= 3 and not info.is_rotation and info.direction is not None
    and info.number not in (29, 30) and not 43 <= info.number <= 47 and not 23 <= info.number <= 28
)
JAW_FAPS = (3, 14, 15)


def fapu_of(face) -> dict[str, float]:
    """FAPU of a FaceModel: {"IRISD", "ES", "ENS", "MNS", "MW"} metres per unit, "AU" radians."""
    return fapu_from_fapu0(fapu0_from_positions(face.feature_point_positions()))


def fap_unit_scale(face) -> np.ndarray:
    """(68,) metres (or radians) per FAP value unit for this head; 0 for FAPs 1, 2."""
    fapu = fapu_of(face)
    return np.array([fapu[u] if u else 0.0 for u in FAP_UNIT_NAME], dtype=np.float64)


def clamp_values(values: np.ndarray) -> np.ndarray:
    """(68,) low-level FAP values clamped to `FAP_LIMITS` (FAPs 1, 2 set to 0); NaN -> 0.

    Infinities are clamped like any value beyond the range (+inf to the upper limit, as
    1e308 is), not zeroed."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0, posinf=np.inf, neginf=-np.inf)
    out = np.clip(v, FAP_LIMITS[:, 0], FAP_LIMITS[:, 1])
    out[:2] = 0.0
    return out


__all__ = ["AU", "FAP_COUNT", "FAP_DIRECTION", "FAP_LIMITS", "FAP_NAME", "FAP_FEATURE_POINT", "FAP_UNIT_NAME",
           "SKIN_TRANSLATION_FAPS", "JAW_FAPS", "fapu_of", "fap_unit_scale", "clamp_values"]
