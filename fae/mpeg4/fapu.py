"""Facial Animation Parameter Units (FAPU) measured on a neutral face.

The standard defines five distances on the neutral face (positions in the face frame:
x toward the face's left, y up, z forward) and divides each by 1024 to get the unit a
FAP value is counted in; angle FAPs use AU = 1e-5 rad:

=======  ====================================================  =======================
IRISD0   iris diameter: upper to lower eyelid, ``3.1.y - 3.3.y``  (right eye 3.2/3.4 when
         the left eye is not given)
ES0      eye separation: pupil centres, ``3.5.x - 3.6.x``
ENS0     eye-nose separation: ``3.5.y - 9.15.y``
MNS0     mouth-nose separation: ``9.15.y - 2.2.y``
MW0      mouth width: outer lip corners, ``8.3.x - 8.4.x``
=======  ====================================================  =======================
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from fae.mpeg4.faps import AU

FAPU0_NAMES = ("IRISD0", "ES0", "ENS0", "MNS0", "MW0")
FAPU_NAMES = ("IRISD", "ES", "ENS", "MNS", "MW", "AU")


def _point(positions: Mapping, name: str) -> np.ndarray:
    if name not in positions:
        raise KeyError(f"FAPU: feature point {name} is missing (have: {', '.join(sorted(positions)) or 'none'})")
    p = np.asarray(positions[name], dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"FAPU: feature point {name} must be a finite (3,) position in metres, got {positions[name]!r}")
    return p


def fapu0_from_positions(positions: Mapping[str, np.ndarray]) -> dict[str, float]:
    """The five neutral-face distances from feature point positions.

    positions  ``{"3.1": (3,) float64, ...}`` in metres, face frame; needs 3.1+3.3 (or
               3.2+3.4), 3.5, 3.6, 9.15, 2.2, 8.3, 8.4.
    Returns ``{"IRISD0", "ES0", "ENS0", "MNS0", "MW0"}`` in metres; ValueError when one is
    not positive (points swapped, or the face is not in the face frame).
    """
    if "3.1" in positions or "3.3" in positions or not ("3.2" in positions and "3.4" in positions):
        irisd0 = _point(positions, "3.1")[1] - _point(positions, "3.3")[1]
    else:
        irisd0 = _point(positions, "3.2")[1] - _point(positions, "3.4")[1]
    fapu0 = {
        "IRISD0": float(irisd0),
        "ES0": float(_point(positions, "3.5")[0] - _point(positions, "3.6")[0]),
        "ENS0": float(_point(positions, "3.5")[1] - _point(positions, "9.15")[1]),
        "MNS0": float(_point(positions, "9.15")[1] - _point(positions, "2.2")[1]),
        "MW0": float(_point(positions, "8.3")[0] - _point(positions, "8.4")[0]),
    }
    for name, value in fapu0.items():
        if not value > 0.0:
            raise ValueError(f"FAPU: {name} = {value:.6g} m is not positive; are the feature points in the face frame "
                             "(x = face's left, y up, z forward) and on a neutral face?")
    return fapu0


def fapu_from_fapu0(fapu0: Mapping[str, float]) -> dict[str, float]:
    """FAPU from the neutral-face distances: each distance / 1024 (metres), plus AU = 1e-5 rad.

    fapu0  ``{"IRISD0", "ES0", "ENS0", "MNS0", "MW0"}`` in metres.
    Returns ``{"IRISD", "ES", "ENS", "MNS", "MW"}`` in metres per unit and ``"AU"`` in radians.
    """
    out = {}
    for name in FAPU0_NAMES:
        if name not in fapu0:
            raise KeyError(f"FAPU: {name} is missing")
        value = float(fapu0[name])
        if not (np.isfinite(value) and value > 0.0):
            raise ValueError(f"FAPU: {name} must be a positive distance in metres, got {fapu0[name]!r}")
        out[name[:-1]] = value / 1024.0
    out["AU"] = AU
    return out
