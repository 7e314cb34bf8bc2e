"""The 68 MPEG-4 Facial Animation Parameters (ISO/IEC 14496-2 FBA), as data.

``FAPS[n - 1]`` is FAP number ``n``. Each :class:`FapInfo` carries the standard's table
row (name, description, FAPU, uni/bidirectional, positive motion, masking group, feature
point(s), quantiser step, I and P arithmetic-coder ranges) plus what fae derives from it:
the unit direction of positive motion in the face frame and, for angle FAPs, the rotation
axis. Face frame (neutral face): x toward the face's own left, y up, z forward (out of the
face toward the viewer), right-handed; metres and radians inside fae.

Ranges: the standard gives the I (intra) and P (predictive) coder ranges in units of the
quantiser step, so the range of a FAP *value* is ``range x quant_step`` (e.g. head_pitch
+-1860 x 170 = +-316200 AU = +-3.16 rad; yaw_l_eyeball +-1200 x 128 AU = +-1.54 rad).
I ranges bound absolute values (an intra frame codes the value itself); P ranges bound
frame-to-frame differences. :attr:`FapInfo.value_range` is therefore the I range times the
quantiser step. tongue_roll (47) follows the published table (+300, +100; unidirectional);
one public decoder uses +-1080/+-420 instead.
"""

from __future__ import annotations

from dataclasses import dataclass

FAP_COUNT = 68
AU = 1e-5  # radians per angle unit

# Face-frame unit vectors of the standard's "positive motion" words.
_MOTION_DIRECTION = {
    "up": (0.0, 1.0, 0.0),
    "down": (0.0, -1.0, 0.0),
    "left": (1.0, 0.0, 0.0),
    "right": (-1.0, 0.0, 0.0),
    "forward": (0.0, 0.0, 1.0),
    "concave upward": (0.0, 1.0, 0.0),  # the tongue's borders rise
}


@dataclass(frozen=True)
class FapInfo:
    """One row of the standard's FAP table.

    number          1..68
    name            e.g. ``"open_jaw"``
    description     the standard's wording
    fapu            ``"MNS" | "MW" | "ES" | "ENS" | "IRISD" | "AU"``; None for FAPs 1, 2
    bidirectional   True for B, False for U; None for FAPs 1, 2
    motion          positive-motion word (``"down"``, ``"left"``, ``"growing"``...); None for 1, 2
    group           masking group 1..10
    feature_points  names ``"group.index"`` of the point(s) it moves; () when none
    quant_step      quantiser step
    i_range, p_range  (min, max) coder ranges in quantiser steps (FAPs 1, 2: blend/intensity 0..63)
    """

    number: int
    name: str
    description: str
    fapu: str | None
    bidirectional: bool | None
    motion: str | None
    group: int
    feature_points: tuple[str, ...]
    quant_step: int
    i_range: tuple[int, int]
    p_range: tuple[int, int]

    @property
    def feature_point(self) -> str | None:
        """The first (main) feature point it moves, or None."""
        return self.feature_points[0] if self.feature_points else None

    @property
    def is_rotation(self) -> bool:
        """True for angle FAPs (eyeball yaw/pitch, tongue roll, head pitch/yaw/roll)."""
        return self.fapu == "AU"

    @property
    def direction(self) -> tuple[float, float, float] | None:
        """Unit vector (3,) in the face frame along which a positive value moves.

        Translations: the feature point's motion. Eyeball/head rotations: the motion of the
        gaze (yaw, pitch) or of the top of the head (roll). None for FAPs 1, 2 and pupil
        dilation (a scalar growth).
        """
        return _MOTION_DIRECTION.get(self.motion) if self.motion else None

    @property
    def rotation_axis(self) -> tuple[float, float, float] | None:
        """Right-handed rotation axis (3,) for a positive value, or None.

        yaw: +y (gaze turns toward +x, the face's left); pitch: +x (gaze turns down);
        roll: +z (top of the head moves toward -x, the face's right). None for tongue_roll
        (its two borders turn about opposite axes) and for translations.
        """
        if not self.is_rotation or "tongue" in self.name:
            return None
        if "yaw" in self.name:
            return (0.0, 1.0, 0.0)
        if "pitch" in self.name:
            return (1.0, 0.0, 0.0)
        return (0.0, 0.0, 1.0)

    @property
    def value_range(self) -> tuple[float, float]:
        """(min, max) of the value in FAPU (or AU) units: I range x quant step."""
        return (float(self.i_range[0] * self.quant_step), float(self.i_range[1] * self.quant_step))


_ROWS = (
    (1, 'viseme', 'Set of values determining the mixture of two visemes (viseme_select1, viseme_select2, viseme_blend, viseme_def)', None, None, None, 1, (), 1, (0, 63), (-63, 63)),
    (2, 'expression', 'Set of values determining the mixture of two expressions (expression_select1, expression_intensity1, expression_select2, expression_intensity2, init_face, expression_def)', None, None, None, 1, (), 1, (0, 63), (-63, 63)),
    (3, 'open_jaw', 'Vertical jaw displacement (does not affect mouth opening)', 'MNS', False, 'down', 2, ('2.1',), 4, (-1080, 1080), (-360, 360)),
    (4, 'lower_t_midlip', 'Vertical top middle inner lip displacement', 'MNS', True, 'down', 2, ('2.2',), 2, (-600, 600), (-180, 180)),
    (5, 'raise_b_midlip', 'Vertical bottom middle inner lip displacement', 'MNS', True, 'up', 2, ('2.3',), 2, (-1860, 1860), (-600, 600)),
    (6, 'stretch_l_cornerlip', 'Horizontal displacement of left inner lip corner', 'MW', True, 'left', 2, ('2.4',), 2, (-600, 600), (-180, 180)),
    (7, 'stretch_r_cornerlip', 'Horizontal displacement of right inner lip corner', 'MW', True, 'right', 2, ('2.5',), 2, (-600, 600), (-180, 180)),
    (8, 'lower_t_lip_lm', 'Vertical displacement of midpoint between left corner and middle of top inner lip', 'MNS', True, 'down', 2, ('2.6',), 2, (-600, 600), (-180, 180)),
    (9, 'lower_t_lip_rm', 'Vertical displacement of midpoint between right corner and middle of top inner lip', 'MNS', True, 'down', 2, ('2.7',), 2, (-600, 600), (-180, 180)),
    (10, 'raise_b_lip_lm', 'Vertical displacement of midpoint between left corner and middle of bottom inner lip', 'MNS', True, 'up', 2, ('2.8',), 2, (-1860, 1860), (-600, 600)),
    (11, 'raise_b_lip_rm', 'Vertical displacement of midpoint between right corner and middle of bottom inner lip', 'MNS', True, 'up', 2, ('2.9',), 2, (-1860, 1860), (-600, 600)),
    (12, 'raise_l_cornerlip', 'Vertical displacement of left inner lip corner', 'MNS', True, 'up', 2, ('2.4',), 2, (-600, 600), (-180, 180)),
    (13, 'raise_r_cornerlip', 'Vertical displacement of right inner lip corner', 'MNS', True, 'up', 2, ('2.5',), 2, (-600, 600), (-180, 180)),
    (14, 'thrust_jaw', 'Depth displacement of jaw', 'MNS', False, 'forward', 2, ('2.1',), 1, (-600, 600), (-180, 180)),
    (15, 'shift_jaw', 'Side to side displacement of jaw', 'MW', True, 'right', 2, ('2.1',), 1, (-1080, 1080), (-360, 360)),
    (16, 'push_b_lip', 'Depth displacement of bottom middle lip', 'MNS', True, 'forward', 2, ('2.3',), 1, (-1080, 1080), (-360, 360)),
    (17, 'push_t_lip', 'Depth displacement of top middle lip', 'MNS', True, 'forward', 2, ('2.2',), 1, (-1080, 1080), (-360, 360)),
    (18, 'depress_chin', 'Upward and compressing movement of the chin (like in sadness)', 'MNS', True, 'up', 2, ('2.10',), 1, (-420, 420), (-180, 180)),
    (19, 'close_t_l_eyelid', 'Vertical displacement of top left eyelid', 'IRISD', True, 'down', 3, ('3.1',), 1, (-1080, 1080), (-600, 600)),
    (20, 'close_t_r_eyelid', 'Vertical displacement of top right eyelid', 'IRISD', True, 'down', 3, ('3.2',), 1, (-1080, 1080), (-600, 600)),
    (21, 'close_b_l_eyelid', 'Vertical displacement of bottom left eyelid', 'IRISD', True, 'up', 3, ('3.3',), 1, (-600, 600), (-240, 240)),
    (22, 'close_b_r_eyelid', 'Vertical displacement of bottom right eyelid', 'IRISD', True, 'up', 3, ('3.4',), 1, (-600, 600), (-240, 240)),
    (23, 'yaw_l_eyeball', 'Horizontal orientation of left eyeball', 'AU', True, 'left', 3, (), 128, (-1200, 1200), (-420, 420)),
    (24, 'yaw_r_eyeball', 'Horizontal orientation of right eyeball', 'AU', True, 'left', 3, (), 128, (-1200, 1200), (-420, 420)),
    (25, 'pitch_l_eyeball', 'Vertical orientation of left eyeball', 'AU', True, 'down', 3, (), 128, (-900, 900), (-300, 300)),
    (26, 'pitch_r_eyeball', 'Vertical orientation of right eyeball', 'AU', True, 'down', 3, (), 128, (-900, 900), (-300, 300)),
    (27, 'thrust_l_eyeball', 'Depth displacement of left eyeball', 'ES', True, 'forward', 3, (), 1, (-600, 600), (-180, 180)),
    (28, 'thrust_r_eyeball', 'Depth displacement of right eyeball', 'ES', True, 'forward', 3, (), 1, (-600, 600), (-180, 180)),
    (29, 'dilate_l_pupil', 'Dilation of left pupil', 'IRISD', True, 'growing', 3, ('3.5',), 1, (-420, 420), (-120, 120)),
    (30, 'dilate_r_pupil', 'Dilation of right pupil', 'IRISD', True, 'growing', 3, ('3.6',), 1, (-420, 420), (-120, 120)),
    (31, 'raise_l_i_eyebrow', 'Vertical displacement of left inner eyebrow', 'ENS', True, 'up', 4, ('4.1',), 2, (-900, 900), (-360, 360)),
    (32, 'raise_r_i_eyebrow', 'Vertical displacement of right inner eyebrow', 'ENS', True, 'up', 4, ('4.2',), 2, (-900, 900), (-360, 360)),
    (33, 'raise_l_m_eyebrow', 'Vertical displacement of left middle eyebrow', 'ENS', True, 'up', 4, ('4.3',), 2, (-900, 900), (-360, 360)),
    (34, 'raise_r_m_eyebrow', 'Vertical displacement of right middle eyebrow', 'ENS', True, 'up', 4, ('4.4',), 2, (-900, 900), (-360, 360)),
    (35, 'raise_l_o_eyebrow', 'Vertical displacement of left outer eyebrow', 'ENS', True, 'up', 4, ('4.5',), 2, (-900, 900), (-360, 360)),
    (36, 'raise_r_o_eyebrow', 'Vertical displacement of right outer eyebrow', 'ENS', True, 'up', 4, ('4.6',), 2, (-900, 900), (-360, 360)),
    (37, 'squeeze_l_eyebrow', 'Horizontal displacement of left eyebrow', 'ES', True, 'right', 4, ('4.1',), 1, (-900, 900), (-300, 300)),
    (38, 'squeeze_r_eyebrow', 'Horizontal displacement of right eyebrow', 'ES', True, 'left', 4, ('4.2',), 1, (-900, 900), (-300, 300)),
    (39, 'puff_l_cheek', 'Horizontal displacement of left cheek', 'ES', True, 'left', 5, ('5.1',), 2, (-900, 900), (-300, 300)),
    (40, 'puff_r_cheek', 'Horizontal displacement of right cheek', 'ES', True, 'right', 5, ('5.2',), 2, (-900, 900), (-300, 300)),
    (41, 'lift_l_cheek', 'Vertical displacement of left cheek', 'ENS', False, 'up', 5, ('5.3',), 2, (-600, 600), (-180, 180)),
    (42, 'lift_r_cheek', 'Vertical displacement of right cheek', 'ENS', False, 'up', 5, ('5.4',), 2, (-600, 600), (-180, 180)),
    (43, 'shift_tongue_tip', 'Horizontal displacement of tongue tip', 'MW', True, 'right', 6, ('6.1',), 1, (-1080, 1080), (-420, 420)),
    (44, 'raise_tongue_tip', 'Vertical displacement of tongue tip', 'MNS', True, 'up', 6, ('6.1',), 1, (-1080, 1080), (-420, 420)),
    (45, 'thrust_tongue_tip', 'Depth displacement of tongue tip', 'MW', True, 'forward', 6, ('6.1',), 1, (-1080, 1080), (-420, 420)),
    (46, 'raise_tongue', 'Vertical displacement of tongue', 'MNS', True, 'up', 6, ('6.2',), 1, (-1080, 1080), (-420, 420)),
    (47, 'tongue_roll', 'Rolling of the tongue into U shape', 'AU', False, 'concave upward', 6, ('6.3', '6.4'), 512, (0, 300), (0, 100)),
    (48, 'head_pitch', 'Head pitch angle from top of spine', 'AU', True, 'down', 7, (), 170, (-1860, 1860), (-600, 600)),
    (49, 'head_yaw', 'Head yaw angle from top of spine', 'AU', True, 'left', 7, (), 170, (-1860, 1860), (-600, 600)),
    (50, 'head_roll', 'Head roll angle from top of spine', 'AU', True, 'right', 7, (), 170, (-1860, 1860), (-600, 600)),
    (51, 'lower_t_midlip_o', 'Vertical top middle outer lip displacement', 'MNS', True, 'down', 8, ('8.1',), 2, (-600, 600), (-180, 180)),
    (52, 'raise_b_midlip_o', 'Vertical bottom middle outer lip displacement', 'MNS', True, 'up', 8, ('8.2',), 2, (-1860, 1860), (-600, 600)),
    (53, 'stretch_l_cornerlip_o', 'Horizontal displacement of left outer lip corner', 'MW', True, 'left', 8, ('8.3',), 2, (-600, 600), (-180, 180)),
    (54, 'stretch_r_cornerlip_o', 'Horizontal displacement of right outer lip corner', 'MW', True, 'right', 8, ('8.4',), 2, (-600, 600), (-180, 180)),
    (55, 'lower_t_lip_lm_o', 'Vertical displacement of midpoint between left corner and middle of top outer lip', 'MNS', True, 'down', 8, ('8.5',), 2, (-600, 600), (-180, 180)),
    (56, 'lower_t_lip_rm_o', 'Vertical displacement of midpoint between right corner and middle of top outer lip', 'MNS', True, 'down', 8, ('8.6',), 2, (-600, 600), (-180, 180)),
    (57, 'raise_b_lip_lm_o', 'Vertical displacement of midpoint between left corner and middle of bottom outer lip', 'MNS', True, 'up', 8, ('8.7',), 2, (-1860, 1860), (-600, 600)),
    (58, 'raise_b_lip_rm_o', 'Vertical displacement of midpoint between right corner and middle of bottom outer lip', 'MNS', True, 'up', 8, ('8.8',), 2, (-1860, 1860), (-600, 600)),
    (59, 'raise_l_cornerlip_o', 'Vertical displacement of left outer lip corner', 'MNS', True, 'up', 8, ('8.3',), 2, (-600, 600), (-180, 180)),
    (60, 'raise_r_cornerlip_o', 'Vertical displacement of right outer lip corner', 'MNS', True, 'up', 8, ('8.4',), 2, (-600, 600), (-180, 180)),
    (61, 'stretch_l_nose', 'Horizontal displacement of left side of nose', 'ENS', True, 'left', 9, ('9.1',), 1, (-540, 540), (-120, 120)),
    (62, 'stretch_r_nose', 'Horizontal displacement of right side of nose', 'ENS', True, 'right', 9, ('9.2',), 1, (-540, 540), (-120, 120)),
    (63, 'raise_nose', 'Vertical displacement of nose tip', 'ENS', True, 'up', 9, ('9.3',), 1, (-680, 680), (-180, 180)),
    (64, 'bend_nose', 'Horizontal displacement of nose tip', 'ENS', True, 'right', 9, ('9.3',), 1, (-900, 900), (-180, 180)),
    (65, 'raise_l_ear', 'Vertical displacement of left ear', 'ENS', True, 'up', 10, ('10.1',), 1, (-900, 900), (-240, 240)),
    (66, 'raise_r_ear', 'Vertical displacement of right ear', 'ENS', True, 'up', 10, ('10.2',), 1, (-900, 900), (-240, 240)),
    (67, 'pull_l_ear', 'Horizontal displacement of left ear', 'ENS', True, 'left', 10, ('10.3',), 1, (-900, 900), (-300, 300)),
    (68, 'pull_r_ear', 'Horizontal displacement of right ear', 'ENS', True, 'right', 10, ('10.4',), 1, (-900, 900), (-300, 300)),

)

FAPS: tuple[FapInfo, ...] = tuple(FapInfo(*row) for row in _ROWS)
_BY_NAME = {info.name: info for info in FAPS}

# Masking groups: group number -> (first FAP, last FAP), inclusive.
MASK_GROUPS: dict[int, tuple[int, int]] = {
    1: (1, 2),
    2: (3, 18),
    3: (19, 30),
    4: (31, 38),
    5: (39, 42),
    6: (43, 47),
    7: (48, 50),
    8: (51, 60),
    9: (61, 64),
    10: (65, 68),
}


def fap_info(number: int) -> FapInfo:
    """The table row of FAP `number` (1..68); ValueError otherwise."""
    if isinstance(number, bool) or not isinstance(number, int) or not 1 <= number <= FAP_COUNT:
        raise ValueError(f"FAP number must be an integer 1..{FAP_COUNT}, got {number!r}")
    return FAPS[number - 1]


def fap_by_name(name: str) -> FapInfo:
    """The table row of the FAP called `name` (e.g. ``"open_jaw"``); KeyError otherwise."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"no FAP is called {name!r}") from None


def _mirror_name(name: str) -> str:
    swap = {"l": "r", "r": "l", "lm": "rm", "rm": "lm"}
    return "_".join(swap.get(part, part) for part in name.split("_"))


def _pairs(partner_of) -> dict[int, int]:
    out = {}
    for info in FAPS:
        other = _BY_NAME.get(partner_of(info.name))
        if other is not None and other.number != info.number:
            out[info.number] = other.number
    return out


# FAP number -> the same motion on the other side of the face (e.g. 6 <-> 7, 19 <-> 20).
# Values copy across unchanged: the standard defines each left/right pair so that equal
# values give the mirror-symmetric motion (stretch both corners outward, gaze both eyes).
MIRROR_FAP: dict[int, int] = _pairs(_mirror_name)

# FAP number -> the inner/outer lip contour FAP moving the corresponding point (4 <-> 51 ... 13 <-> 60).
LIP_PARTNER_FAP: dict[int, int] = {
    **_pairs(lambda n: n + "_o"),
    **_pairs(lambda n: n[:-2] if n.endswith("_o") else n),
}


def mirror_fap(number: int) -> int:
    """The left/right partner of FAP `number`; the number itself for midline FAPs."""
    fap_info(number)
    return MIRROR_FAP.get(number, number)
