"""FAP 1 (visemes) and FAP 2 (expressions) as low-level FAP values, and their blending.

The standard leaves a viseme's or expression's face to the decoder; fae's tables below
give each as low-level FAP values (FAPU units), authored from the standard's phoneme and
expression descriptions (fae.mpeg4.highlevel): open jaw and lip shapes for visemes; brow,
lid, cheek and lip-corner motion for expressions. Blending follows the standard:

    viseme:     v1 * blend/63 + v2 * (1 - blend/63)
    expression: e1 * intensity1/63 + e2 * intensity2/63

and the result is added to the frame's low-level FAPs.
"""

from __future__ import annotations

import numpy as np

from fae.mpeg4.faps import FAP_COUNT
from fae.mpeg4.highlevel import BLEND_MAX, EXPRESSIONS


def _table(rows: dict[int, dict[int, float]], count: int, convert=lambda pose: pose) -> np.ndarray:
    out = np.zeros((count, FAP_COUNT))
    for code, faps in rows.items():
        for fap, value in convert(faps).items():
            out[code, fap - 1] = value
    return out


def _sym(**pairs) -> dict[int, float]:
    """Expand symmetric entries: key 'f6_7' -> FAPs 6 and 7 with the same value."""
    out = {}
    for key, value in pairs.items():
        for n in key[1:].split("_"):
            out[int(n)] = float(value)
    return out


# How far the mandible carries the lower lip's and the corners' feature points, in their
# FAPs' units per unit of open_jaw (measured on the generic head and rounded: 1.18-1.24
# and 0.48; the Xface streams send 1.27 and 0.59). The standard's lip FAPs are displacements that the
# jaw does not change (fae.animate.mapping), so a pose that opens the jaw with its lips
# riding on it sends these as well: `jaw_carried`.
JAW_CARRIES = {5: -1.25, 10: -1.25, 11: -1.25, 52: -1.2, 57: -1.2, 58: -1.2, 12: -0.5, 13: -0.5, 59: -0.5, 60: -0.5}


def jaw_carried(pose: dict[int, float]) -> dict[int, float]:
    """FAP -> value: `pose` (open_jaw at pose[3], the lip values relative to where the jaw
    carries the lips) with the lip values as the standard's displacements from neutral."""
    jaw = float(pose.get(3, 0.0))
    out = dict(pose)
    if jaw:
        for fap, ratio in JAW_CARRIES.items():
            out[fap] = float(out.get(fap, 0.0)) + ratio * jaw
    return out


# (15, 68) viseme code -> low-level FAP values (FAPU units), lips relative to the jaw. PP
# closes the lips along their width, the midlip FAPs and the lateral ones (8-11, 55-58)
# together: with the midlips' alone (60 / 120 MNS) the lips met in the middle only, teeth
# showing 0.8 mm either side, and pressed through each other there (4 frames of 20 held)
VISEME_FAPS = _table({
    0: {},                                                                              # sil
    1: _sym(f4=30, f5=60, f51=20, f52=40, f8_9=25, f10_11=50, f55_56=15, f57_58=30, f16_17=40, f3=0),  # PP: lips pressed
    2: _sym(f3=60, f5=200, f52=160, f16=-120, f4=-40, f51=-30),                       # FF: lower lip to teeth
    3: _sym(f3=160, f4=-60, f51=-60, f6_7=20, f53_54=20, f44=300, f45=250),           # TH: tongue between teeth
    4: _sym(f3=140, f4=-40, f51=-40, f6_7=30, f53_54=30, f44=350),                    # DD
    5: _sym(f3=200, f4=-60, f5=-80, f51=-50, f52=-60, f46=250),                       # kk
    6: _sym(f3=120, f4=-80, f5=-80, f51=-80, f52=-80, f6_7=-120, f53_54=-120, f16_17=180),  # CH: rounded, protruded
    7: _sym(f3=60, f4=-50, f5=-40, f51=-50, f52=-40, f6_7=80, f53_54=80),             # SS: teeth close, spread
    8: _sym(f3=140, f4=-40, f51=-40, f44=300),                                        # nn
    9: _sym(f3=120, f6_7=-150, f53_54=-150, f16_17=140, f4=-40, f51=-40),             # RR: rounded
    10: _sym(f3=500, f4=-100, f51=-100, f6_7=40, f53_54=40),                          # aa: wide open
    11: _sym(f3=280, f4=-80, f51=-80, f6_7=120, f53_54=120, f12_13=40, f59_60=40),     # E
    12: _sym(f3=180, f4=-60, f51=-60, f6_7=160, f53_54=160, f12_13=60, f59_60=60),     # ih: spread
    13: _sym(f3=380, f6_7=-200, f53_54=-200, f16_17=160, f4=-80, f51=-80),            # oh: round, open
    14: _sym(f3=200, f6_7=-260, f53_54=-260, f16_17=240, f4=-40, f51=-40),            # ou: small round
}, 15, jaw_carried)

# expression -> low-level FAP values (FAPU units) at full intensity (63), lips relative to
# the jaw, after the standard's descriptions (fae.mpeg4.highlevel) and the muscle actions of
# FACS: joy = lip corners back and up, cheeks lifted, lower lids raised, jaw open; sadness =
# inner brows up, upper lids lowered, lip corners down, chin raised; anger = brows down and
# together, upper lids raised, lips pressed (along their width, as PP's), nostrils flared;
# fear = brows up and together,
# upper lids wide, mouth stretched open; disgust = upper lip raised (more on the left), nose
# wrinkled, cheeks lifted; surprise = brows up, upper lids wide, jaw dropped, lips rounded.
# Magnitudes are clearly visible yet anatomically possible: a fifth to a third of each FAP's
# range (the brows' raise at most 300 ENS, 16 mm on the generic head, where a face lifts its
# brows 10-15 mm; the Xface streams' fear sends 100); joy's corners rise 200 MNS over the
# jaw, which carries them down 100 as it opens: 1.5 mm up on the generic head (at 120 they
# stayed level, a flat open mouth). fap_streams/expressions.fap plays these poses, with a
# head motion each.
EXPRESSION_POSES: dict[str, dict[int, float]] = {
    "joy": _sym(f3=200, f4=-60, f51=-60, f5=-80, f52=-80, f6_7=150, f53_54=150, f12_13=200, f59_60=200,
                f41_42=150, f21_22=150, f19_20=80, f33_34=40),
    "sadness": _sym(f31_32=200, f33_34=60, f35_36=-80, f37_38=60, f19_20=300, f12_13=-100, f59_60=-100,
                    f5=60, f52=60, f18=120),
    "anger": _sym(f31_32=-200, f33_34=-120, f35_36=-40, f37_38=150, f19_20=-150, f21_22=100, f4=30, f51=30,
                  f5=60, f52=60, f8_9=25, f10_11=50, f55_56=25, f57_58=50, f6_7=-40, f53_54=-40, f61_62=60),
    "fear": _sym(f31_32=250, f33_34=180, f35_36=100, f37_38=80, f19_20=-250, f21_22=-50, f3=150, f6_7=100,
                 f53_54=100, f12_13=-60, f59_60=-60, f5=-60, f52=-60),
    "disgust": _sym(f4=-150, f51=-150, f8=-180, f9=-80, f55=-180, f56=-80, f12=-40, f59=-40, f61_62=120, f63=100,
                    f41_42=120, f21_22=150, f31_32=-100, f37_38=60, f19_20=100),
    "surprise": _sym(f31_32=250, f33_34=300, f35_36=250, f19_20=-300, f3=400, f4=-50, f51=-50, f5=-100, f52=-100,
                     f6_7=-60, f53_54=-60),
}

# (7, 68) expression code (fae.mpeg4.highlevel.EXPRESSIONS) -> low-level FAP values as the
# standard's displacements from neutral (the lips where the jaw carries them added)
EXPRESSION_FAPS = _table({e.code: EXPRESSION_POSES[e.name] for e in EXPRESSIONS if e.name in EXPRESSION_POSES},
                         len(EXPRESSIONS), jaw_carried)


def _pair(record, kind: str) -> tuple[tuple[int, float], tuple[int, float]]:
    weights = getattr(record, "weights", None)
    if callable(weights):
        return weights()
    r = [int(x) for x in record]
    if kind == "viseme":
        w = r[2] / BLEND_MAX
        return (r[0], w), (r[1], 1.0 - w)
    return (r[0], r[1] / BLEND_MAX), (r[2], r[3] / BLEND_MAX)


def highlevel_values(viseme=None, expression=None) -> np.ndarray:
    """(68,) low-level FAP values (FAPU units) of a FAP 1 and a FAP 2 record (either may be None).

    viseme      fae.mpeg4.highlevel.Viseme or (select1, select2, blend[, def])
    expression  fae.mpeg4.highlevel.Expression or (select1, intensity1, select2, intensity2[, ...])
    Codes out of range raise ValueError naming the record.
    """
    out = np.zeros(FAP_COUNT)
    for record, table, kind in ((viseme, VISEME_FAPS, "viseme"), (expression, EXPRESSION_FAPS, "expression")):
        if record is None:
            continue
        for code, weight in _pair(record, kind):
            if not 0 <= code < len(table):
                raise ValueError(f"{kind}: code {code} is outside 0..{len(table) - 1}")
            out += table[code] * float(np.clip(weight, 0.0, 1.0))
    return out


def faps_in_stream(frames) -> set[int]:
    """Numbers of the low-level FAPs (3-68) that `frames` (fae.io.fap.FapFrame iterable) set
    to a value other than 0, themselves or through a FAP 1 viseme or FAP 2 expression record."""
    used = np.zeros(FAP_COUNT, dtype=bool)
    records = set()
    for frame in frames:
        used |= np.asarray(frame.mask, dtype=bool) & (np.asarray(frame.values, dtype=np.float64) != 0.0)
        for record in (frame.viseme, frame.expression):
            if record is not None:
                records.add((record is frame.viseme, record))
    for is_viseme, record in records:
        try:
            values = highlevel_values(viseme=record) if is_viseme else highlevel_values(expression=record)
        except ValueError:  # a code out of range: the player names it
            continue
        used |= values != 0.0
    used[:2] = False
    return {int(i) + 1 for i in np.flatnonzero(used)}
