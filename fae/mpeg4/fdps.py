"""The 84 MPEG-4 feature points (FDPs, ISO/IEC 14496-2 FBA), named ``"group.index"``.

Each :class:`FeaturePoint` has the standard's description, the FAPs acting on it and its
mirror partner. Left/right are the face's own (left = +x). The standard numbers most
pairs left-odd/right-even (3.1/3.2, 4.5/4.6, 10.1/10.2 ...), but not all: group 2 puts the
left point first on an even index (2.4/2.5), 8.9/8.10, 9.4-9.7 and 11.2/11.3 put the right
point first, and the eye corners are named by the side of the image (3.7 "left corner of
left eye" mirrors 3.12 "right corner of right eye"). The partners are therefore derived
from the descriptions (swap left/right, map referenced points to their partners), and the
tests check the result against the index convention where it holds.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from fae.mpeg4.faps import FAPS

FEATURE_POINT_COUNT = 84

# group -> number of points in it (groups 2..11).
GROUP_SIZES: dict[int, int] = {2: 14, 3: 14, 4: 6, 5: 4, 6: 4, 7: 1, 8: 10, 9: 15, 10: 10, 11: 6}

_ROWS = (
    ('2.1', 'Bottom of the chin'),
    ('2.2', 'Middle point of inner upper lip contour'),
    ('2.3', 'Middle point of inner lower lip contour'),
    ('2.4', 'Left corner of inner lip contour'),
    ('2.5', 'Right corner of inner lip contour'),
    ('2.6', 'Midpoint between 2.2 and 2.4 in the inner upper lip contour'),
    ('2.7', 'Midpoint between 2.2 and 2.5 in the inner upper lip contour'),
    ('2.8', 'Midpoint between 2.3 and 2.4 in the inner lower lip contour'),
    ('2.9', 'Midpoint between 2.3 and 2.5 in the inner lower lip contour'),
    ('2.10', 'Chin boss'),
    ('2.11', 'Chin left corner'),
    ('2.12', 'Chin right corner'),
    ('2.13', 'Left corner of jaw bone'),
    ('2.14', 'Right corner of jaw bone'),
    ('3.1', 'Center of upper inner left eyelid'),
    ('3.2', 'Center of upper inner right eyelid'),
    ('3.3', 'Center of lower inner left eyelid'),
    ('3.4', 'Center of lower inner right eyelid'),
    ('3.5', 'Center of the pupil of left eye'),
    ('3.6', 'Center of the pupil of right eye'),
    ('3.7', 'Left corner of left eye'),
    ('3.8', 'Left corner of right eye'),
    ('3.9', 'Center of lower outer left eyelid'),
    ('3.10', 'Center of lower outer right eyelid'),
    ('3.11', 'Right corner of left eye'),
    ('3.12', 'Right corner of right eye'),
    ('3.13', 'Center of upper outer left eyelid'),
    ('3.14', 'Center of upper outer right eyelid'),
    ('4.1', 'Right corner of left eyebrow'),
    ('4.2', 'Left corner of right eyebrow'),
    ('4.3', 'Uppermost point of the left eyebrow'),
    ('4.4', 'Uppermost point of the right eyebrow'),
    ('4.5', 'Left corner of left eyebrow'),
    ('4.6', 'Right corner of right eyebrow'),
    ('5.1', 'Center of the left cheek'),
    ('5.2', 'Center of the right cheek'),
    ('5.3', 'Left cheek bone'),
    ('5.4', 'Right cheek bone'),
    ('6.1', 'Tip of the tongue'),
    ('6.2', 'Center of the tongue body'),
    ('6.3', 'Left border of the tongue'),
    ('6.4', 'Right border of the tongue'),
    ('7.1', 'Top of spine (center of head rotation)'),
    ('8.1', 'Middle point of outer upper lip contour'),
    ('8.2', 'Middle point of outer lower lip contour'),
    ('8.3', 'Left corner of outer lip contour'),
    ('8.4', 'Right corner of outer lip contour'),
    ('8.5', 'Midpoint between 8.3 and 8.1 in outer upper lip contour'),
    ('8.6', 'Midpoint between 8.4 and 8.1 in outer upper lip contour'),
    ('8.7', 'Midpoint between 8.3 and 8.2 in outer lower lip contour'),
    ('8.8', 'Midpoint between 8.4 and 8.2 in outer lower lip contour'),
    ('8.9', "Right high point of Cupid's bow"),
    ('8.10', "Left high point of Cupid's bow"),
    ('9.1', 'Left nostril border'),
    ('9.2', 'Right nostril border'),
    ('9.3', 'Nose tip'),
    ('9.4', 'Bottom right edge of nose'),
    ('9.5', 'Bottom left edge of nose'),
    ('9.6', 'Right upper edge of nose bone'),
    ('9.7', 'Left upper edge of nose bone'),
    ('9.8', 'Top of the upper teeth'),
    ('9.9', 'Bottom of the lower teeth'),
    ('9.10', 'Bottom of the upper teeth'),
    ('9.11', 'Top of the lower teeth'),
    ('9.12', 'Middle lower edge of nose bone (or nose bump)'),
    ('9.13', 'Left lower edge of nose bone'),
    ('9.14', 'Right lower edge of nose bone'),
    ('9.15', 'Bottom middle edge of nose'),
    ('10.1', 'Top of left ear'),
    ('10.2', 'Top of right ear'),
    ('10.3', 'Back of left ear'),
    ('10.4', 'Back of right ear'),
    ('10.5', 'Bottom of left ear lobe'),
    ('10.6', 'Bottom of right ear lobe'),
    ('10.7', 'Lower contact point between left lobe and face'),
    ('10.8', 'Lower contact point between right lobe and face'),
    ('10.9', 'Upper contact point between left ear and face'),
    ('10.10', 'Upper contact point between right ear and face'),
    ('11.1', 'Middle border between hair and forehead'),
    ('11.2', 'Right border between hair and forehead'),
    ('11.3', 'Left border between hair and forehead'),
    ('11.4', 'Top of skull'),
    ('11.5', 'Hair thickness over 11.4'),
    ('11.6', 'Back of skull'),
)

# Rotation FAPs have no feature point in the FAP table; these are the points they act on.
_ROTATION_ACTS_ON = {"3.5": (23, 25, 27), "3.6": (24, 26, 28), "7.1": (48, 49, 50)}


@dataclass(frozen=True)
class FeaturePoint:
    """One MPEG-4 feature point.

    name         ``"group.index"``, e.g. ``"2.4"``
    group, index the two numbers of the name
    description  the standard's wording
    faps         FAP numbers acting on it (sorted; () for points no FAP moves)
    side         +1 face's left (+x), -1 face's right, 0 midline
    mirror       name of the partner on the other side (itself for midline points)
    """

    name: str
    group: int
    index: int
    description: str
    faps: tuple[int, ...]
    side: int
    mirror: str


_SWAP = {"left": "right", "right": "left", "Left": "Right", "Right": "Left"}
_SIDE_WORD = re.compile(r"\b(left|right)\b", re.IGNORECASE)
_POINT_REF = re.compile(r"\b(\d+\.\d+)\b")


def _swap_sides(text: str) -> str:
    return _SIDE_WORD.sub(lambda m: _SWAP[m.group(0)], text)


def _derive_mirrors(rows) -> dict[str, str]:
    by_description = {description: name for name, description in rows}
    mirror: dict[str, str] = {}
    # Pass 1: points described without references to other points.
    for name, description in rows:
        if _POINT_REF.search(description):
            continue
        partner = by_description.get(_swap_sides(description)) if _SIDE_WORD.search(description) else name
        if partner is None:
            raise RuntimeError(f"feature point {name}: no mirror for {description!r}")
        mirror[name] = partner
    # Pass 2: "Midpoint between 2.2 and 2.4 ..." mirrors to the midpoint of the mirrored points.
    for name, description in rows:
        if name in mirror:
            continue
        swapped = _POINT_REF.sub(lambda m: mirror[m.group(1)], _swap_sides(description))
        partner = by_description.get(swapped)
        if partner is None:
            raise RuntimeError(f"feature point {name}: no mirror for {description!r}")
        mirror[name] = partner
    return mirror


def _side(name: str, description: str, mirror: dict[str, str], sides: dict[str, int]) -> int:
    if mirror[name] == name:
        return 0
    words = _SIDE_WORD.findall(description)
    if words:  # the last side word names the part the point lies on ("Right corner of left eyebrow")
        return 1 if words[-1].lower() == "left" else -1
    refs = [ref for ref in _POINT_REF.findall(description) if sides.get(ref)]
    return sides[refs[0]]


def _build() -> tuple[FeaturePoint, ...]:
    mirror = _derive_mirrors(_ROWS)
    acting: dict[str, set[int]] = {name: set() for name, _ in _ROWS}
    for info in FAPS:
        for point in info.feature_points:
            acting[point].add(info.number)
    for point, numbers in _ROTATION_ACTS_ON.items():
        acting[point].update(numbers)
    sides: dict[str, int] = {}
    for name, description in sorted(_ROWS, key=lambda row: bool(_POINT_REF.search(row[1]))):
        sides[name] = _side(name, description, mirror, sides)
    points = []
    for name, description in _ROWS:
        group, index = (int(part) for part in name.split("."))
        points.append(FeaturePoint(name, group, index, description, tuple(sorted(acting[name])), sides[name], mirror[name]))
    return tuple(points)


FEATURE_POINTS: tuple[FeaturePoint, ...] = _build()
_BY_NAME = {point.name: point for point in FEATURE_POINTS}


def feature_point(name: str) -> FeaturePoint:
    """The feature point called `name` (``"group.index"``, e.g. ``"3.5"``); KeyError otherwise."""
    try:
        return _BY_NAME[str(name)]
    except KeyError:
        raise KeyError(f"no MPEG-4 feature point is called {name!r} (expected 'group.index', groups 2..11)") from None


def mirror_point(name: str) -> str:
    """The name of the mirror partner of feature point `name` (itself on the midline)."""
    return feature_point(name).mirror


def face_part(name: str) -> str | None:
    """The part of the face feature point `name` marks, the points a marker places together
    ("mouth": the lips' outer and inner contours; "jaw": chin and jaw bone; "nose";
    "eye_l" / "eye_r"; "brow_l" / "brow_r"; "cheek_l" / "cheek_r"; "ear_l" / "ear_r";
    "head"), or None (tongue, teeth 9.8-9.11, the spine's point)."""
    p = feature_point(name)
    side = "_l" if p.side > 0 else "_r"
    if p.group == 8 or (p.group == 2 and 2 <= p.index <= 9):
        return "mouth"
    if p.group == 9 and 8 <= p.index <= 11:
        return None
    return {2: "jaw", 9: "nose", 11: "head", 3: "eye" + side, 4: "brow" + side, 5: "cheek" + side,
            10: "ear" + side}.get(p.group)
