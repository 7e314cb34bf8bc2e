"""The layout of a head's FAP -> control mapping (`FaceModel.fap_mapping`), shared by
calibration, which writes it (fae.animate.calibrate), and the controls, which read it
(fae.animate.controls).

    FORMAT_VERSION    the solver the mapping was calibrated for (another moves the feature
                      points by other amounts: a mismatch means calibrating again)
    JAW_CONTROLS      jaw controls at the end of each row: angle (rad), thrust (m), shift (m)
    JAW_OPEN          open_jaw, which does not move the lips (see below)
    LIP_FAPS          the lip FAPs whose points open_jaw holds
    LIP_PAIRS         (inner, outer) lip FAPs that move one lip at one place (see below)
    LOWERING_FIELD_FAPS  FAPs with a pull field of their own for negative values (see below)
    field_faps(face)  the pull fields of this head, in control order: FAP k, or -k for the
                      field of FAP k's negative values

The standard defines open_jaw (FAP 3) as a "vertical jaw displacement (does not affect
mouth opening)": the lip FAPs give their feature points' displacement from the neutral
face whatever the jaw does, and a stream opens the mouth by lowering the lower lip as far
as the jaw goes (the shared Xface streams send raise_b_midlip = -1.27 x open_jaw, which is
how far the jaw carries 2.3 on the generic head: 1.24). The skin of the lower lip rides on
the mandible, so each lip FAP's controls take back what the jaw carried its point by:
`jaw_follow` (68,) in the mapping is that motion along the FAP's direction, in the FAP's
units per unit of open_jaw (fae.animate.calibrate, fae.animate.controls). Added to the jaw instead,
a stream's lower lip dropped twice as far as it asks (17 mm for 10 in xface_joy),
creasing the chin.

Each inner lip FAP (4-13) has an outer twin (51-60) on the same lip, a few millimetres
away on a real face; streams send the two alike (the Xface streams: outer = inner for the
corners and the stretch, 0.8-2.7 x for the upper lip). Where the two points lie together
(2.4 and 8.3 are one point of the generic head's mouth corner), each FAP's controls
move both, and the pair sent alike moved the corner twice as far as either asks: a spike
pulled up from each corner of a smile, its edges stretched 7x. `pair_overlap` (68,) in
the mapping is how far a FAP's controls move its twin's point along the twin's
direction, over how far they move its own (the two ways averaged, 0..1; measured on the
linear response by calibration), and `merge_lip_pairs` (fae.animate.controls) scales a
pair sent the same way so that the larger request is met at its point, not their sum:
one FAP alone, or two points far apart, are unchanged.

A brow raised as far as the standard's range goes (+-900 ENS, 48 mm on the generic head;
expressions.fap's surprise asks 13-16 mm) lifted the forehead as a slab with a folded
ridge where its pull ended, and round bumps about the brow's three points lifted it in
lumps: a raise now pulls along the brow's line, shared with its neighbours, and lifts the
forehead up to the crown (fae.animate.calibrate.brow_raise_weights). The same field,
negative, pulled the whole forehead down over the eyes, so the brow FAPs
(LOWERING_FIELD_FAPS) lower with a field of their own, the round bump about the point.
"""

from __future__ import annotations

from fae.animate.ears import EAR_FAPS
from fae.mpeg4.faptables import FAP_FEATURE_POINT, JAW_FAPS, SKIN_TRANSLATION_FAPS

# 10: a brow raise pulls along the brow's line (a hat between its neighbours' points) and
# lifts the forehead up to the crown;
# 9: a cheek raise (41, 42) pulls the lower eyelids half as hard;
# 8: a lip's points between two others pull with fields spanning its margin between them;
# 7: an upper lid closes by unfolding its crease and the brow's underside, the skin's
# edges are kept within strain limits, and crease moves are inelastic;
# 6: the brows raise with a long pull shared among them and lower with a field of their own;
# 5: inner and outer lip FAPs merged where their points overlap (pair_overlap); 4: lip FAPs are displacements the jaw does not change (jaw_follow), 2.1 at the gnathion; 3: the skin solver with the fold guard, crease smoothing and lip contact (fae.sim.folds)
# and pull fields preferred to muscles; 2: implicit anchors, blended holds and derived ear
# tables
FORMAT_VERSION = 10
JAW_CONTROLS = 3
JAW_OPEN = 3
# the inner (4-13) and outer (51-60) lip FAPs
LIP_FAPS = tuple(range(4, 14)) + tuple(range(51, 61))
# each inner lip FAP and its outer twin: same lip, same direction (4 <-> 51 ... 13 <-> 60)
LIP_PAIRS = tuple((k, k + 47) for k in range(4, 14))
# the brows' raises (31-36), whose negative values have a pull field of their own
LOWERING_FIELD_FAPS = tuple(range(31, 37))


def field_faps(face) -> list[int]:
    """The pull fields of this head, in control order: FAP k for each skin-bound translation
    except the jaw's and the ears' (fae.animate.ears), then -k, the field of FAP k's
    negative values, for those of LOWERING_FIELD_FAPS."""
    own = [k for k in SKIN_TRANSLATION_FAPS
           if k not in JAW_FAPS and k not in EAR_FAPS and FAP_FEATURE_POINT[k - 1] in face.feature_points
           and face.feature_points[FAP_FEATURE_POINT[k - 1]].part == "skin"]
    return own + [-k for k in own if k in LOWERING_FIELD_FAPS]
