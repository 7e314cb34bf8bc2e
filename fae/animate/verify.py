"""Check a head's FAP response: each feature-point-bound FAP alone, at half its range.

For every low-level FAP that translates a skin feature point (`SKIN_TRANSLATION_FAPS`:
3-22, 31-42, 51-68), the Player holds the value R/2 (R: the positive limit the Player
clamps to, `FAP_LIMITS[:, 1]`, the standard's I range in FAPU) until the skin settles, and
the feature point's motion is compared with the standard's: value x FAPU along the FAP's
direction. `ratio` is the motion along that direction over the expected distance; a FAP
passes when |ratio - 1| <= `tolerance` (15 %).
"""

from __future__ import annotations

import numpy as np

from fae.mpeg4.faptables import (FAP_DIRECTION, FAP_FEATURE_POINT, FAP_LIMITS, FAP_NAME, SKIN_TRANSLATION_FAPS,
                                   fap_unit_scale)
from fae.mpeg4.faps import FAP_COUNT

TOLERANCE = 0.15


def settled_skin(player, values: np.ndarray, fps: float = 25.0, settled: float = 5e-6,
                 max_frames: int = 60) -> np.ndarray:
    """(V, 3) metres: the skin once FAP `values` (68,) held from the neutral face has settled
    (no vertex moving more than `settled` metres in a frame of 1/fps s, or `max_frames`
    frames), stepped without the lids' lead as the calibration settles it (Player.lead_off);
    the player is left at rest."""
    player.reset()
    previous = None
    with player.lead_off():
        for _ in range(max_frames):
            skin = player.step(values, dt=1.0 / fps)
            if previous is not None and np.abs(skin - previous).max() < settled:
                break
            previous = skin
    player.reset()
    return skin


def verify_faps(player, faps=None, tolerance: float = TOLERANCE, frames: int = 60, fps: float = 25.0,
                settled: float = 5e-6) -> list[dict]:
    """Per FAP: {"fap", "name", "feature_point", "value", "expected_m", "measured_m", "ratio", "ok"}.

    player  a fae.animate.player.Player on the head to check (reset before each FAP)
    faps    FAP numbers to check (default: every FDP-bound one the head has); others raise ValueError
    frames  at most this many frames of 1/fps s are played per FAP; it stops earlier once no
            skin vertex moves more than `settled` metres in a frame
    value is in FAPU units; expected_m and measured_m are (3,) lists, metres in the head frame.
    """
    face = player.face
    unit = fap_unit_scale(face)
    available = [k for k in SKIN_TRANSLATION_FAPS
                 if FAP_FEATURE_POINT[k - 1] in face.feature_points
                 and face.feature_points[FAP_FEATURE_POINT[k - 1]].part == "skin"]
    if faps is None:
        faps = available
    for k in faps:
        if k not in available:
            raise ValueError(f"FAP {k}: not a feature-point translation this head can check "
                             f"(expected one of {available[0]}..{available[-1]}: {available})")
    rest = face.feature_point_positions()
    out = []
    for k in faps:
        fdp = FAP_FEATURE_POINT[k - 1]
        value = FAP_LIMITS[k - 1, 1] / 2.0
        values = np.zeros(FAP_COUNT)
        values[k - 1] = value
        skin = settled_skin(player, values, fps=fps, settled=settled, max_frames=frames)
        expected = FAP_DIRECTION[k - 1] * value * unit[k - 1]
        measured = face.surface_point_position(face.feature_points[fdp], skin) - rest[fdp]
        ratio = float(measured @ FAP_DIRECTION[k - 1]) / float(value * unit[k - 1])
        out.append({"fap": int(k), "name": FAP_NAME[k - 1], "feature_point": fdp, "value": float(value),
                    "expected_m": [float(x) for x in expected], "measured_m": [float(x) for x in measured],
                    "ratio": ratio, "ok": bool(abs(ratio - 1.0) <= tolerance)})
    return out


def passed_fraction(report: list[dict]) -> float:
    """Fraction of the FAPs of a `verify_faps` report that passed (0 for an empty report)."""
    return float(np.mean([r["ok"] for r in report])) if report else 0.0
