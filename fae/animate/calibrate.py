"""Calibration: derive each head's FAP -> control mapping by probing its own simulation.

Choice per FAP group (every low-level FAP 3-68 drives something):
- jaw (3, 14, 15): mandible pose. open_jaw combines the hinge rotation with a forward slide
  of the condyles (least squares, the slide penalized) so that the chin 2.1 moves straight
  down; thrust_jaw slides it forward (+z), shift_jaw sideways (x). The skin follows
  through its holds (fae.sim.build.jaw_weights).
- lips, chin, cheeks, brows, nose (4-13, 16-18, 31-42, 51-64): a least-squares combination of
  the head's muscles (contractions >= 0) plus one directional pull field of the FAP's own
  (centred on its feature point, along the standard direction, Wendland fall-off over the
  skin's geodesic distance, radius a fraction of ES0; a lip's points between two others
  span its margin between them instead: lip_margin_weight), the field's use penalized so that
  muscles do what they can; the field supplies what no muscle can (lip protrusion 16/17,
  lip lowering, nostrils, the off-axis remainder).
- eyelids (19-22): the pull field only (no muscle in the model moves them).
- ears (65-68): FaceDefTables derived from the head (fae.animate.ears), exact, not simulated.
- eyeballs, pupils, tongue, head (23-30, 43-50): rigid poses, see fae.animate.rigid.

Procedure: (1) linear response: the skin's stiffness matrix at rest (springs k n n^T plus
anchors: fae.sim.reference.ReferenceSolver.rest_stiffness) is factorized once; each control's rest force field gives the skin's
displacement per unit control (with the unsimulated skin carried by its hold). (2) per
FAP and side, bounded least squares (scipy lsq_linear) for the controls moving its feature
point by one metre along the standard direction while, for a sided FAP, its mirror point
stays still (those rows weighted by how far apart the two points are, see MIRROR_NEAR). (3) nonlinear correction: the real solver is run at +-half range (the
operating amplitude verify-faps checks) for FAPs in batches whose footprints, grown by two
edge rings, do not overlap (the jaw FAPs alone), each batch on its footprint alone (grown
by PART_RINGS rings; the rest of the skin held, fae.sim.build.skin_model's `only`: the
same steps on 40 % of the particles on average; the jaw's on the whole skin); the
settled displacement along the direction is measured and the table scale at +-half and
full range multiplied by expected / measured (clipped to [0.5, 2] per pass; `passes` 3 by default, 1 from a similar
head's mapping); the upper lids' closing (FULL_RANGE_FAPS) is measured at its positive
limit too, for its full-range scale. (4) refinement: a FAP still off by more than REFINE_TOLERANCE is measured
again at its new scale, up to REFINE_PASSES times; where the skin snaps between two settled
states (a nose or lip pull that stretches edges to the fold guard's strain limit drags the
tissue beside it along: raise_nose on a bust went from 0.8x to 1.45x of its value between
0.40 and 0.46 of its range), the scale is searched between the largest that fell short and
the smallest that overshot, and each FAP keeps the measured scale nearest its value (the
last pass leaves a FAP already within REFINE_TOLERANCE at the scale it was measured at:
a step more might cross a snap unmeasured; the three busts: 43-45 of 50 FAPs within 15 %
before, 48-49 after). pair_overlap is measured in the last full pass, before the
refinement. The result, arrays only,
goes into `FaceModel.fap_mapping`:

    layout       (4,) int: muscle count, field count, jaw controls (3), format version
    field_faps   (K,) int: FAP of each pull field, in control order (-k: the field of FAP
                 k's negative values, fae.animate.mapping)
    field_radius (K,) float metres
    gain_pos     (68, C) float: controls per FAP unit for positive values
    gain_neg     (68, C) float: controls per FAP unit of |v| for negative values
    table_values (68, 5) float FAPU: -R, -R/2, 0, R/2, R (R: the positive translation limit)
    table_scale  (68, 5) float: multiplier of the linear controls at those values
    jaw_follow   (68,) float: how far open_jaw alone carries each lip FAP's point along the
                 FAP's direction, FAP units per open_jaw unit (fae.animate.mapping), measured
                 with the real solver at +half open_jaw
    hold_scale   (68,) float: the multiplier of a lip FAP's controls where they take back
                 more than the FAP asks (u and v of opposite signs, or v = 0: open_jaw sent
                 alone), calibrated so that open_jaw alone at +half range leaves the lip
                 points where the jaw found them (the table scales are measured with the
                 other lip in the way, these with the mouth opening)
    pair_overlap (68,) float 0..1: how far an inner or outer lip FAP moves its twin's
                 point (LIP_PAIRS) over how far it moves its own, both ways and both signs
                 averaged, measured with the real solver at +-half range in the last pass
                 (fae.animate.mapping)
Controls C: the head's muscles, then the pull fields, then jaw (angle rad, thrust m, shift m).
"""

from __future__ import annotations

import copy
import queue
import threading
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

import numpy as np
import scipy.sparse as sp
from scipy.optimize import lsq_linear
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from fae.animate.controls import FapControls
from fae.animate.mapping import (FORMAT_VERSION, JAW_CONTROLS, JAW_OPEN, LIP_FAPS, LIP_PAIRS,
                                 LOWERING_FIELD_FAPS, field_faps)
from fae.mpeg4.faptables import (FAP_DIRECTION, FAP_FEATURE_POINT, FAP_LIMITS, JAW_FAPS,
                                   SKIN_TRANSLATION_FAPS, fap_unit_scale, fapu_of)
from fae.mpeg4.faps import FAP_COUNT
from fae.mpeg4.fdps import mirror_point
from fae.cores import workers
from fae.linalg import symmetric_splu
from fae.mesh import adjacency
from fae.sim.build import (EYE_CLEARANCE, PullField, dilate, eyeball_sphere, mesh_edges, skin_model,
                           skin_positions)
from fae.sim.reference import ReferenceSolver

FIELD_ONLY_FAPS = (19, 20, 21, 22)
CHEEK_LIFT_FAPS = (41, 42)
CHEEK_LID_SHARE = 0.5  # of a cheek raise's pull on the lower eyelids (see pull_fields)
# pull-field radius per FAP, in units of ES0
_FIELD_RADIUS_ES = {**{k: 0.16 for k in (4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 16, 17)},
                    **{k: 0.18 for k in range(51, 61)}, 18: 0.3,
                    **{k: 0.15 for k in (19, 20, 21, 22)}, **{k: 0.3 for k in range(31, 39)},
                    **{k: 0.45 for k in (39, 40, 41, 42)}, **{k: 0.2 for k in (61, 62, 63, 64)}}
# the controls' costs in the least squares: a pull field (a smooth bump around the FAP's own
# feature point) is preferred to the muscles, whose Waters zones reach the feature point at
# their edge and then need large contractions that crease the skin beside it (the depressor
# labii at 2.3 for xface_joy's lowered lower lip: 183 triangles folded or creased, 109 with
# the fields preferred; verify-faps 50/50 and 49/50)
MUSCLE_COST = 0.5
# a sided FAP's mirror point should stay still: its motion counts like the FAP's own error
# when the two are at least MIRROR_FAR x ES0 apart, not at all below MIRROR_NEAR x ES0 (the
# lower lip's 8.7 and 8.8, 0.42 ES0 apart, are one piece of tissue)
MIRROR_NEAR = 0.4
MIRROR_FAR = 0.7
FIELD_COST = 0.05
CONTROL_SCALE = 0.01  # metres
# passes of the nonlinear correction from neutral table scales, and from another head's
COLD_PASSES = 3
WARM_PASSES = 1
# then FAPs off by more than REFINE_TOLERANCE are measured again, at most REFINE_PASSES times
REFINE_PASSES = 4
REFINE_TOLERANCE = 0.1
# a probe's amplitude (+-1: half range, 2: the positive limit) -> the table_scale columns it
# sets: a half-range probe sets its half and full range, but a FAP of FULL_RANGE_FAPS has
# its positive limit measured on its own
SCALE_COLUMNS = {1.0: [3, 4], -1.0: [1, 0], 2.0: [4]}
# FAPs measured at their positive limit (1080) too: the upper lids' closing. Streams blink
# at 1024 (the lid down by IRISD0, onto the lower lid), where the lid's response to the
# scale of half range had fallen to 0.85: a held blink left a 1.8 mm slit of eyeball showing
FULL_RANGE_FAPS = (19, 20)
SETTLE_THREADS = 4  # at most; Warp's CPU kernels release the GIL
PART_RINGS = 3  # edge rings of free skin around a batch's footprint in its probes
# a warm-started lip FAP whose table scale ended this far (as a share) from its start's is
# measured again on the whole skin, at both scales (and, where neither lands within
# REFINE_TOLERANCE, at the next scale they suggest), and keeps the nearest: a probe on part
# of the skin holds the rest, and the lips press on each other (marble_bust's lower lip
# corners' raises: measured short there and raised from 5.6 to 8.6 / 7.2, 1.80 / 1.58x
# their value on the whole skin; 1.06 / 1.19x at the start's scale, 1.02x at 4.7)
WHOLE_CHECK_SHIFT = 0.2
# a probe's settle ends once the points it measures move less than SETTLE_TOLERANCE of their
# motion in each of two frames running, from SETTLE_MIN_FRAMES on (at most `settle_frames`;
# two, since a lid's skin of lower drag may turn round at an overshoot): on Demosthenes
# about 15 frames instead of 20 on average at 0.2 %, the measured motion within 3 % of the
# 20th frame's for 95 % of the probes (a fixed 14 frames: 8 %). At 1 % the busts'
# calibrations take 10-25 % less time and verify-faps passes as many FAPs in all (marble /
# Demosthenes / wreath 49 / 50 / 49 against 48 / 49 / 50; frames and accuracy not measured again)
SETTLE_MIN_FRAMES = 8
SETTLE_TOLERANCE = 0.01
# FAPs probed alone: the mouth corners' raise, which a batch mate whose footprint does not
# meet its own on the linear response still moves through the lips' contact
ALONE_FAPS = (12, 13, 59, 60)
# each lip's margins through their feature points, from one corner to the other
# (inner: 2.x, outer: 8.x), and the FAPs that move a point between two others up or down:
# their fields span the margin between the neighbours (lip_margin_weight)
LIP_MARGINS = (("2.5", "2.7", "2.2", "2.6", "2.4"), ("2.5", "2.9", "2.3", "2.8", "2.4"),
               ("8.4", "8.6", "8.1", "8.5", "8.3"), ("8.4", "8.8", "8.2", "8.7", "8.3"))
LIP_MARGIN_FAPS = (4, 5, 8, 9, 10, 11, 51, 52, 55, 56, 57, 58)
MARGIN_SAMPLES = 9  # points along each piece of a margin whose nearest skin seeds its distance
MARGIN_MIN_GAP = 0.001  # m: a margin's point this close across the face to a neighbour has no hat
# how many times farther a raise's pull reaches above its point than below: the corners'
# (see pull_fields)
RAISE_REACH = {k: 2.0 for k in ALONE_FAPS}
# the brows' points across the face, right outer to left outer, and how far a brow raise's
# lift reaches up the forehead, in radii of its field (brow_raise_weights)
BROW_LINE = ("4.6", "4.4", "4.2", "4.1", "4.3", "4.5")
BROW_LIFT_REACH = 9.0
BROW_MIDLINE_RAMP = 0.5


def edge_length_graph(face) -> sp.csr_matrix:
    """(V, V) sparse: skin edge lengths (metres) between adjacent vertices (upper triangle)."""
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    e = mesh_edges(np.asarray(face.skin_faces))
    w = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)
    return sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(V), len(V))).tocsr()


def geodesic_distance(face, point, limit: float, graph: sp.csr_matrix | None = None) -> np.ndarray:
    """(V,) metres along skin edges from a surface point (inf beyond `limit`).

    graph: `edge_length_graph(face)`, when already at hand."""
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    G = edge_length_graph(face) if graph is None else graph
    tri = np.asarray(face.skin_faces)[point.triangle]
    p = face.surface_point_position(point)
    d = dijkstra(G, directed=False, indices=tri, limit=limit)
    return np.min(d + np.linalg.norm(V[tri] - p, axis=1)[:, None], axis=0)


def pull_fields(face, fapu: dict[str, float], graph: sp.csr_matrix | None = None) -> list[PullField]:
    """The pull fields of `face`, one per FAP of `field_faps`, in that order (graph:
    `edge_length_graph(face)`, when already at hand)."""
    es0 = fapu["ES"] * 1024.0
    names = list(face.region_names)
    region = np.asarray(face.skin_region)
    faces = np.asarray(face.skin_faces)
    graph = edge_length_graph(face) if graph is None else graph
    brows = brow_raise_weights(face, es0, graph)
    out = []
    for f in field_faps(face):
        k = abs(f)
        name = f"fap{k}" if f > 0 else f"fap{k}_lowering"
        point = face.feature_points[FAP_FEATURE_POINT[k - 1]]
        lid = eyelid_weight(face, k, graph)
        if lid is not None:
            out.append(PullField(name, FAP_DIRECTION[k - 1], lid, drag=LID_DRAG))
            continue
        if f in brows:
            out.append(PullField(name, FAP_DIRECTION[k - 1], brows[f]))
            continue
        radius = _FIELD_RADIUS_ES.get(k, 0.2) * es0
        w = lip_margin_weight(face, k, radius, graph)
        if w is None:
            reach = RAISE_REACH.get(f, 1.0)  # a lowering field (f < 0): the round bump
            d = geodesic_distance(face, point, radius * reach, graph)
            w = _wendland(np.minimum(d / radius, 1.0))
            if reach != 1.0:
                # a corner raised alone squashed the skin above it into folds that the guard
                # rocked against: the skin above the point comes along, fading `reach` times
                # farther than below it
                above = np.asarray(face.skin_vertices)[:, 1] > face.surface_point_position(point)[1]
                w = np.where(above, _wendland(np.minimum(d / (radius * reach), 1.0)), w)
        if k in CHEEK_LIFT_FAPS:
            # the cheek pushes the lower lid up from below more than it pulls it: pulled as
            # hard as the cheek, the lid's margin rolled off the eyeball and showed its
            # lining (a fit of marble_bust smiling as xface_joy does: 10 mm^2 of its back
            # seen, 0 at half); not pulled at all, the outer eye corner tore open between
            # the risen cheek and the lid left behind (the generic head at the FAP's limit:
            # 109 mm^2, 17 at half)
            w[np.isin(region, [i for i, n in enumerate(names) if n.startswith("eyelid_lower")])] *= CHEEK_LID_SHARE
        # upper-lip points never pull the lower lip and vice versa
        own = {names[i] for i in region[faces[point.triangle]]}
        for word, other in (("upper", "lower"), ("lower", "upper")):
            if own and all(word in n for n in own):
                w[np.isin(region, [i for i, n in enumerate(names) if other in n])] = 0.0
        out.append(PullField(name, FAP_DIRECTION[k - 1], w))
    return out


def lip_margin_weight(face, k: int, radius: float, graph: sp.csr_matrix | None = None) -> np.ndarray | None:
    """(V,) pull-field weights of lip FAP k, or None for a FAP that moves no point between
    two others of a lip's margin up or down (LIP_MARGIN_FAPS), a head lacking the points, or
    one whose point is not between its neighbours across the face (within MARGIN_MIN_GAP)
    (graph: `edge_length_graph(face)`, when at hand).

    A round bump about each point moved the points alone: a lip's three points raised
    alike (xface_anger's upper lip at -90, 2.6 mm) moved its edge 2.6-3.4 mm at the points
    and 1.3 mm between them, and the edge came out as a row of teeth. Along the lip the
    weight is a hat in x instead, 1 at the FAP's point and 0 at the neighbouring points of
    its margin (LIP_MARGINS), so the fields of a margin's middle three points add up to 1
    between the outer two of them (towards the corners the corners' own fields take over);
    across the lip it falls as a Wendland function of the skin's distance (along its edges)
    from the margin between those neighbours, to 0 at `radius` metres."""
    own = FAP_FEATURE_POINT[k - 1]
    margin = next((m for m in LIP_MARGINS if own in m), None) if k in LIP_MARGIN_FAPS else None
    fp = face.feature_point_positions()
    if margin is None or not all(n in fp for n in margin):
        return None
    i = margin.index(own)
    point = fp[own]
    lo, hi = sorted((fp[margin[i - 1]], fp[margin[i + 1]]), key=lambda p: p[0])  # whichever way x runs
    if not (lo[0] + MARGIN_MIN_GAP < point[0] < hi[0] - MARGIN_MIN_GAP):
        return None
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    x = V[:, 0]
    hat = np.where(x < point[0], (x - lo[0]) / (point[0] - lo[0]), (hi[0] - x) / (hi[0] - point[0]))
    d = line_distance(face, np.array([lo, point, hi]), [own], radius, graph)
    return np.clip(hat, 0.0, 1.0) * _wendland(np.minimum(d / radius, 1.0))


def line_distance(face, P: np.ndarray, names: list[str], limit: float,
                  graph: sp.csr_matrix | None = None) -> np.ndarray:
    """(V,) metres along skin edges from the polyline through P (k, 3) metres (inf beyond
    `limit`): seeded on the skin of the regions of feature points `names` nearest to
    MARGIN_SAMPLES points along each straight piece (the line runs along those regions: a
    lip's margin, the brow; the skin beside it is not the line). graph:
    `edge_length_graph(face)`, when at hand."""
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    t = np.linspace(0.0, 1.0, MARGIN_SAMPLES)[:, None]
    samples = np.vstack([P[i] + t * (P[i + 1] - P[i]) for i in range(len(P) - 1)] or [P])
    region = np.asarray(face.skin_region)
    faces = np.asarray(face.skin_faces)
    own = np.unique(np.concatenate([region[faces[face.feature_points[n].triangle]] for n in names]))
    candidates = np.flatnonzero(np.isin(region, own))
    seeds = candidates[np.unique(cKDTree(V[candidates]).query(samples)[1])]
    G = edge_length_graph(face) if graph is None else graph
    return dijkstra(G, directed=False, indices=seeds, min_only=True, limit=limit)


def _wendland(r: np.ndarray) -> np.ndarray:
    """Wendland's C2 fall-off over r in [0, 1]: 1 at 0, 0 at 1 and beyond."""
    r = np.minimum(r, 1.0)
    return (1.0 - r) ** 4 * (4.0 * r + 1.0)


def brow_raise_weights(face, es0: float, graph: sp.csr_matrix) -> dict[int, np.ndarray]:
    """(V,) pull-field weights of each brow raise (LOWERING_FIELD_FAPS the head has), made
    together (graph: `edge_length_graph(face)`).

    The brows' points (BROW_LINE, across the face) lie on one line, the brow. Along it,
    each raise's weight is a hat in x, 1 at its own point and 0 at its neighbours' (past
    the outer points it stays 1, fading as a Wendland function over the radius from
    _FIELD_RADIUS_ES): the six raises sent alike lift the brow evenly, where round bumps
    about each point lifted it in lumps with grooves between (a surprise's brows at 60 %
    of their lift between the points) and lifted the forehead where two bumps overlapped
    twice. Across it, the weight falls with the skin's distance (along its edges) from the
    line: below, as a Wendland function over the radius (the brow's underside and the
    upper lid come along); above, as a raised cosine over BROW_LIFT_REACH times the radius,
    so that the forehead rises with the brow and is squeezed gently up to the crown
    instead of buckling into a ridge where a shorter pull ends (a surprise's 16 mm raise
    with a reach of 5 radii: a ridge across the top of the forehead)."""
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    fp = face.feature_point_positions()
    line = [n for n in BROW_LINE if n in fp and face.feature_points[n].part == "skin"]
    found = [k for k in LOWERING_FIELD_FAPS if FAP_FEATURE_POINT[k - 1] in line]
    if not found:
        return {}
    P = np.array([fp[n] for n in line])
    order = np.argsort(P[:, 0])
    line, P = [line[i] for i in order], P[order]
    radius = _FIELD_RADIUS_ES[found[0]] * es0
    reach = BROW_LIFT_REACH * radius
    d = line_distance(face, P, line, reach, graph)  # from the brow (its underside is not the brow)
    above = V[:, 1] > np.interp(V[:, 0], P[:, 0], P[:, 1])
    across = np.where(above, 0.5 * (1.0 + np.cos(np.pi * np.minimum(d / reach, 1.0))), _wendland(d / radius))
    across = np.where(np.isfinite(d), across, 0.0)
    x = V[:, 0]

    def ramp(a: float, b: float) -> np.ndarray:
        # 0 at neighbour x = a, 1 at the point's x = b; across the midline (the inner brows)
        # over BROW_MIDLINE_RAMP of the way about the middle, so a brow raised alone leaves
        # its mirror where it was (the ramp over the whole way took it 16 % as far)
        if a * b < 0.0:
            half = 0.5 * BROW_MIDLINE_RAMP * (b - a)
            a, b = 0.5 * (a + b) - half, 0.5 * (a + b) + half
        return (x - a) / (b - a)

    out = {}
    for k in found:
        i = line.index(FAP_FEATURE_POINT[k - 1])
        xi = P[i, 0]
        # a hat in x, 1 at the point, 0 at the neighbours; past an outer point 1, fading
        lo = ramp(P[i - 1, 0], xi) if i > 0 else _wendland(np.maximum(xi - x, 0.0) / radius)
        hi = ramp(P[i + 1, 0], xi) if i < len(P) - 1 else _wendland(np.maximum(x - xi, 0.0) / radius)
        hat = np.clip(np.where(x < xi, lo, hi), 0.0, 1.0)
        out[k] = hat * across
    return out


# eyelid FAP -> (the lid's region, its eye's inner and outer corners, the eyeball part, the
# brow point over an upper lid); the lid's own point is the FAP's (3.1-3.4)
_EYELIDS = {19: ("eyelid_upper_l", "3.11", "3.7", "eye_l", "4.3"), 20: ("eyelid_upper_r", "3.12", "3.8", "eye_r", "4.4"),
            21: ("eyelid_lower_l", "3.11", "3.7", "eye_l", None), 22: ("eyelid_lower_r", "3.12", "3.8", "eye_r", None)}
# the skin an upper lid draws down with it as it closes: its own front and the forehead's
# underside, up to the brow
_LID_UNFOLDS_INTO = ("forehead",)
# how far up that skin comes along: a share of the way from the margin to the brow's point
# (all of it hooded the lid with the brow's underside; 0.7 folded the lid more)
LID_UNFOLD_REACH = 0.85
# 1/s: the drag of the skin a lid's pull moves (the skin's is 70, fae.sim.build). A blink
# sent as 512, 1024, 1024, 512 (the shared streams') left a third of the eye open at its
# deepest with the skin's: the lid reached 0.40, 0.75, 0.88 of a step in its first three
# frames. With 30: 0.59, 0.85, 0.96, and the same settled lid; the stable substep stays
# above 20 ms (two per 25 fps frame)
LID_DRAG = 30.0


def eyelid_weight(face, k: int, graph: sp.csr_matrix | None = None) -> np.ndarray | None:
    """(V,) pull-field weights of eyelid FAP k (19-22), or None when the head lacks the lid's
    region or its eye's corner points (graph: `edge_length_graph(face)`, when at hand).

    A round bump about the lid's middle point brought its middle down in a V and left the
    eye open on both sides of it (closed at 1024, the lids met only at 3.1). The lid
    closes along its whole margin instead: a vertex at t along the line from the inner to
    the outer corner (0..1) weighs s(t) / s(t at the lid's point), s(t) = sqrt(1 - (2t -
    1)^2), the opening's elliptical height there, so every margin point meets the other
    lid when the middle does and the corners stay. Across the lid the weight is 1 at and
    beyond the margin and falls as a Wendland function of the height above (below, for a
    lower lid) the margin, to 0 at the region's extent over the margin's middle, and of
    the depth behind the margin, to 0 at the opening's height (the lining deep in the
    socket stays). The eyeball, a collider of the skin (fae.sim.build), keeps the closing
    lid in front of it.

    An upper lid covers the eye by unfolding the skin of its crease and under the brow,
    about twice its own height at rest: weighted by the height above the margin, its few
    millimetres of front stretched to four times their length while the crease stayed. Its
    front (the skin farther than EYE_CLEARANCE from the eyeball: not the lining) weighs
    instead at least s(t) x a raised cosine of the distance along the front skin from the
    margin, 1 there, 0 at LID_UNFOLD_REACH of the way to the brow's point, so the lid, its
    crease and the brow's underside come down together, each stretched a little."""
    if k not in _EYELIDS:
        return None
    region_name, inner_name, outer_name, eye_name, brow_name = _EYELIDS[k]
    names = list(face.region_names)
    fp = face.feature_point_positions()
    lid_name = FAP_FEATURE_POINT[k - 1]
    if region_name not in names or not all(n in fp for n in (inner_name, outer_name, lid_name)):
        return None
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    region = np.asarray(face.skin_region)
    inside = region == names.index(region_name)
    a, b, lid = fp[inner_name], fp[outer_name], fp[lid_name]
    span = b[0] - a[0]
    if abs(span) < 1e-6 or not inside.any():
        return None

    def height(t):
        return np.sqrt(np.clip(1.0 - (2.0 * t - 1.0) ** 2, 0.0, 1.0))

    t, t_lid = (V[:, 0] - a[0]) / span, (lid[0] - a[0]) / span
    if not 0.0 < t_lid < 1.0:
        return None
    shape = height(t) / height(t_lid)
    opening = lid[1] - (a[1] + t_lid * (b[1] - a[1]))  # signed: + upper lid, - lower
    margin_y = a[1] + t * (b[1] - a[1]) + opening * shape
    margin_z = a[2] + t * (b[2] - a[2]) + (lid[2] - (a[2] + t_lid * (b[2] - a[2]))) * shape
    above = (V[:, 1] - margin_y) * np.sign(opening)  # away from the eye's opening
    middle = inside & (np.abs(t - t_lid) < 0.15)
    extent = float(above[middle].max()) if middle.any() else 0.0
    if extent <= 0.0 or abs(opening) < 1e-6:
        return None
    r = np.clip(above / extent, 0.0, 1.0)
    q = np.clip((margin_z - V[:, 2]) / abs(opening), 0.0, 1.0)
    w = np.clip(shape, 0.0, 1.0) * (1.0 - r) ** 4 * (4.0 * r + 1.0) * (1.0 - q) ** 4 * (4.0 * q + 1.0)
    w = np.where(inside, w, 0.0)
    sphere = eyeball_sphere(face, eye_name)
    if brow_name is None or brow_name not in fp or sphere is None:
        return w
    centre, radius = sphere
    front = inside & (np.linalg.norm(V - centre, axis=1) - radius >= EYE_CLEARANCE)
    seeds = np.flatnonzero(front & (w > 0.95))
    unfolding = (front | np.isin(region, [names.index(n) for n in _LID_UNFOLDS_INTO if n in names]))
    unfolding &= (above > -0.04 * abs(opening)) & (t > -0.2) & (t < 1.2)
    if len(seeds) == 0:
        return w
    G = edge_length_graph(face) if graph is None else graph
    keep = sp.diags(unfolding.astype(np.float64))
    d = dijkstra(keep @ G @ keep, directed=False, indices=seeds, min_only=True)
    reach = d[np.argmin(np.linalg.norm(V - fp[brow_name], axis=1))]
    if not np.isfinite(reach) or reach <= 0.0:
        return w
    along = 0.5 * (1.0 + np.cos(np.pi * np.clip(d / (LID_UNFOLD_REACH * reach), 0.0, 1.0)))
    return np.maximum(w, np.where(unfolding & np.isfinite(d), np.clip(shape, 0.0, 1.0) * along, 0.0))


class _Probe:
    """Linear response of a head's simulation, as skin displacement fields (V, 3)."""

    def __init__(self, face, model):
        self.face, self.model = face, model
        self.ref = ReferenceSolver(model)
        K, self.free = self.ref.rest_stiffness()
        self.lu = symmetric_splu(K)
        self.q0 = self.ref.a["particle_q"].astype(np.float64)
        self.fixed = self.ref.inv_mass == 0.0
        self.eye = np.tile(np.eye(3), (2, 1, 1))
        self.rest = np.asarray(face.skin_vertices, dtype=np.float64)
        faces = np.asarray(face.skin_faces)
        # feature point -> (skin vertices (3,), bary (3,))
        self.fdp = {name: (faces[p.triangle], np.asarray(p.bary, dtype=np.float64))
                    for name, p in face.feature_points.items() if p.part == "skin"}

    def _skin_response(self, force: np.ndarray, q: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        return self._skin_moved(self.lu.solve(force.reshape(-1)[self.free]), q, R, t)

    def _skin_moved(self, u_free: np.ndarray, q: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(V, 3) skin displacement when the free particles at q move by u_free (3F,)."""
        u = np.zeros(3 * self.model.particle_count)
        u[self.free] = u_free
        return skin_positions(self.model, q + u.reshape(-1, 3), R, t) - self.rest

    def fdp_motion(self, u: np.ndarray, name: str) -> np.ndarray:
        verts, bary = self.fdp[name]
        return bary @ u[verts]

    def muscle_responses(self, count: int) -> list[np.ndarray]:
        """The skin's response (V, 3) to each of the first `count` controls at unit
        activation, all solved at once (one triangular solve with `count` right-hand sides)."""
        if count == 0:
            return []
        t = np.zeros((2, 3))
        at_rest = self.ref.forces(self.q0, np.zeros(self.model.muscle_count), self.eye, t).reshape(-1)[self.free]
        per_unit = self.ref.muscle_force_matrix(self.q0, self.eye, t)[self.free][:, :count].toarray()
        U = self.lu.solve(per_unit + at_rest[:, None])
        return [self._skin_moved(U[:, m], self.q0, self.eye, t) for m in range(count)]

    def jaw_response(self, rig, which: int, eps: float) -> np.ndarray:
        T = rig.jaw(*(eps if i == which else 0.0 for i in range(3)))
        R, t = self.eye.copy(), np.zeros((2, 3))
        R[1], t[1] = T[:3, :3], T[:3, 3]
        # the fixed ring sits on its hold; the free particles respond to it and to their anchors
        q = self.q0.copy()
        q[self.fixed] = self.ref.holds(R, t)[self.fixed]
        f = self.ref.forces(q, np.zeros(self.model.muscle_count), R, t)
        return self._skin_response(f, q, R, t) / eps


def _control_responses(probe: _Probe, rig, count: int) -> list[np.ndarray]:
    """The skin's linear response (V, 3) to each control: the first `count` (muscles and
    fields) per unit activation, then the jaw's angle, thrust and shift per radian / metre."""
    return probe.muscle_responses(count) + [probe.jaw_response(rig, 0, 1e-3), probe.jaw_response(rig, 1, 1e-4),
                                            probe.jaw_response(rig, 2, 1e-4)]


def _solve(J: np.ndarray, target: np.ndarray, cost: np.ndarray, lower: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(J, axis=0)
    ok = norms > 1e-9
    out = np.zeros(J.shape[1])
    if not np.any(ok):
        return out
    # the penalty counts each unit of control as CONTROL_SCALE metres of error times its cost,
    # so weak muscles (tiny response) are not driven to huge contractions
    A = np.vstack([J[:, ok], np.diag(cost[ok] * CONTROL_SCALE)])
    b = np.concatenate([target, np.zeros(ok.sum())])
    lo = np.where(lower[ok] == 0.0, 0.0, -np.inf)
    res = lsq_linear(A, b, bounds=(lo, np.full(ok.sum(), np.inf)))
    out[ok] = res.x
    return out


def calibrate(face, device: str = "cpu", passes: int | None = None, settle_frames: int = 20, start: dict | None = None,
              early_stop: bool = True):
    """A copy of FaceModel `face` with `fap_mapping` filled (see module docstring).

    early_stop: a probe ends once its points are still (SETTLE_TOLERANCE), else it runs
    all `settle_frames`. Whether a point counts as still is a threshold, which a small
    change of the head flips: the probe then measures a few frames' creep more or less, and
    its table scale moves by as much (a brow's 10 % for a change of the philtrum). Without
    it, the mapping follows the head continuously: what a template build wants, where
    every test is tuned to the mapping, and speed matters less than for a user's head.

    start: the mapping of a similar head (the template a personalized head was adapted
    from): its table scales, the solver's nonlinearity measured there, start the
    correction, which then needs WARM_PASSES passes instead of `passes` (default 3)."""
    from fae.animate.rigid import RigidRig
    from fae.sim.solver import SkinSolver

    fapu = fapu_of(face)
    unit = fap_unit_scale(face)
    fields = pull_fields(face, fapu)
    # (the lids' pulls are scaled on the lid moving freely: at its limit the standard asks a
    # closing lid 5 % past the lower lid, which the lids' contact forbids; measured against
    # it, Demosthenes' lid scale rose from 1.43 to 3.9 and its lining rolled out)
    model = skin_model(face, device=device, fields=fields, lid_contact=False)
    probe = _Probe(face, model)
    rig = RigidRig(face, fapu)
    nm, nf = len(face.muscles), len(fields)
    C = nm + nf + JAW_CONTROLS
    field_of = {k: nm + i for i, k in enumerate(field_faps(face))}

    responses = _control_responses(probe, rig, nm + nf)

    gain_pos, gain_neg = np.zeros((FAP_COUNT, C)), np.zeros((FAP_COUNT, C))
    fdp_pos = face.feature_point_positions()
    es0 = fapu["ES"] * 1024.0
    for k in SKIN_TRANSLATION_FAPS:
        fdp = FAP_FEATURE_POINT[k - 1]
        if fdp not in probe.fdp or (k not in JAW_FAPS and k not in field_of):
            continue
        if k in JAW_FAPS:
            cols = {3: [nm + nf, nm + nf + 1], 14: [nm + nf + 1], 15: [nm + nf + 2]}[k]
            cost = np.array({3: [0.001, 0.3], 14: [0.001], 15: [0.001]}[k])
            lower_pos = np.array({3: [0.0, -np.inf], 14: [0.0], 15: [-np.inf]}[k])
        elif k in FIELD_ONLY_FAPS:
            cols, cost, lower_pos = [field_of[k]], np.array([FIELD_COST]), np.array([-np.inf])
        else:
            cols = list(range(nm)) + [field_of[k]]
            cost = np.array([MUSCLE_COST] * nm + [FIELD_COST])
            lower_pos = np.array([0.0] * nm + [-np.inf])
        mirror = mirror_point(fdp)
        # a left FAP moves the left side only: its mirror point is asked to stay still, the
        # less so the nearer it is (points near the midline share their tissue)
        weight = 0.0
        if mirror != fdp and mirror in probe.fdp:
            apart = np.linalg.norm(fdp_pos[fdp] - fdp_pos[mirror]) / es0
            weight = float(np.clip((apart - MIRROR_NEAR) / (MIRROR_FAR - MIRROR_NEAR), 0.0, 1.0))

        def motion(cols):
            J = np.column_stack([probe.fdp_motion(responses[c], fdp) for c in cols])
            if weight > 0.0:
                J = np.vstack([J, weight * np.column_stack([probe.fdp_motion(responses[c], mirror) for c in cols])])
            return J

        J = motion(cols)
        target = np.zeros(len(J))
        target[:3] = FAP_DIRECTION[k - 1]
        gain_pos[k - 1, cols] = _solve(J, target, cost, lower_pos) * unit[k - 1]
        if FAP_LIMITS[k - 1, 0] < 0:
            if -k in field_of:  # lowered with a field of its own
                cols = [field_of[-k] if c == field_of[k] else c for c in cols]
                J = motion(cols)
            gain_neg[k - 1, cols] = _solve(J, -target, cost, lower_pos) * unit[k - 1]

    half = FAP_LIMITS[:, 1] / 2.0
    table_values = np.column_stack([-2 * half, -half, np.zeros(FAP_COUNT), half, 2 * half])
    table_scale = np.ones((FAP_COUNT, 5))
    jaw_follow = np.zeros(FAP_COUNT)
    hold_scale = np.ones(FAP_COUNT)
    if warm_start_usable(start):
        table_scale = np.asarray(start["table_scale"], dtype=np.float64).copy()
        jaw_follow = np.asarray(start["jaw_follow"], dtype=np.float64).copy()
        hold_scale = np.asarray(start["hold_scale"], dtype=np.float64).copy()
        passes = WARM_PASSES if passes is None else passes
    passes = COLD_PASSES if passes is None else passes
    mapping = {
        "layout": np.array([nm, nf, JAW_CONTROLS, FORMAT_VERSION], dtype=np.int64),
        "field_faps": np.array(field_faps(face), dtype=np.int64),
        "field_radius": np.array([_FIELD_RADIUS_ES.get(abs(k), 0.2) * fapu["ES"] * 1024 for k in field_faps(face)]),
        "gain_pos": gain_pos, "gain_neg": gain_neg, "table_values": table_values, "table_scale": table_scale,
        "jaw_follow": jaw_follow, "hold_scale": hold_scale, "pair_overlap": np.zeros(FAP_COUNT),
    }

    # Nonlinear correction with the real solver: each FAP is probed at its operating
    # amplitudes (+-half range, the value verify-faps checks) and its table scaled so the
    # settled motion of its feature point along the standard direction is the expected one.
    # FAPs whose footprints (with a margin ring) do not overlap are probed together.
    faps = [k for k in SKIN_TRANSLATION_FAPS if np.any(gain_pos[k - 1]) or np.any(gain_neg[k - 1])]
    batches, footprint = _disjoint_batches(face, model, faps, responses, gain_pos, gain_neg, unit)
    twin_of = {**{i: o for i, o in LIP_PAIRS}, **{o: i for i, o in LIP_PAIRS}}
    controls_face = copy.copy(face)
    # the settles of one pass do not depend on each other (each starts from rest and holds only
    # its batch's FAPs): they run on every core, each thread with its own solver and state
    threads = workers(SETTLE_THREADS)
    # a batch without a jaw FAP moves only its footprint: its probes run on that part of the
    # skin alone (PART_RINGS more rings free around it; the rest held, as it is at rest),
    # the same steps on 40 % of the particles on average (half the thread time); the jaw's
    # on the whole skin
    batch_of = {k: i for i, b in enumerate(batches) for k in b}
    A = adjacency(np.asarray(face.skin_faces), len(face.skin_vertices))
    parts = {-1: model}  # batch -> its part, made by the first job that needs it
    contexts = {i: queue.SimpleQueue() for i in range(-1, len(batches))}
    # the whole model's first step runs every kernel alone, before any thread launches one
    contexts[-1].put((SkinSolver(model), settle_scratch(model)))
    part_locks = {i: threading.Lock() for i in range(len(batches))}

    def part_of(key: int):
        with part_locks[key]:
            if key not in parts:
                only = dilate(np.any([footprint[k] for k in batches[key]], axis=0), A, PART_RINGS)
                parts[key] = skin_model(face, device=device, fields=fields, like=model, only=only,
                                        lid_contact=False)
        return parts[key]

    def settled(job):
        # job: (side, FAPs, values (68,), kind "probe" / "hold" / "whole", FapControls)
        key = -1 if job[3] in ("hold", "whole") or any(k in JAW_FAPS for k in job[1]) else batch_of[job[1][0]]
        part = model if key < 0 else part_of(key)
        try:
            solver, scratch = contexts[key].get_nowait()
        except queue.Empty:
            solver, scratch = SkinSolver(part), settle_scratch(part)
        try:
            return settle(part, solver, job[4], job[2], rig, frames=settle_frames, scratch=scratch,
                          watch=None if job[3] == "hold" or not early_stop else watch_points(job[1]))
        finally:
            contexts[key].put((solver, scratch))

    def watch_points(todo: list[int]) -> tuple | None:
        # the points a probe of FAPs `todo` measures (their own, and their lip twins' and, for
        # open_jaw, the lips' points, which it also reads) for `settle` to watch
        names = [(FAP_FEATURE_POINT[k - 1], k) for k in todo]
        names += [(FAP_FEATURE_POINT[twin_of[k] - 1], twin_of[k]) for k in todo if k in twin_of]
        if JAW_OPEN in todo:
            names += [(FAP_FEATURE_POINT[k - 1], k) for k in LIP_FAPS]
        names = [(n, k) for n, k in names if n in probe.fdp]
        if not names:
            return None
        return (np.array([probe.fdp[n][0] for n, _ in names]), np.array([probe.fdp[n][1] for n, _ in names]),
                np.array([FAP_DIRECTION[k - 1] for _, k in names]))

    def moved_along(point: str, k: int, skin: np.ndarray) -> float:
        # metres feature point `point` moved along FAP k's direction in the settled skin
        return float((face.surface_point_position(face.feature_points[point], skin) - fdp_pos[point])
                     @ FAP_DIRECTION[k - 1])

    def expected_motion(k: int, side: float) -> float:
        # metres FAP k's probe on `side` should move its point (amplitude |side| half-ranges)
        return abs(side) * half[k - 1] * unit[k - 1]

    def controls_now(scale: np.ndarray | None = None, jaw_free: bool = False) -> FapControls:
        # the controls of the mapping as it stands, on copies of its arrays: the jobs run
        # while the scales of other FAPs change (table scale `scale` instead, where given;
        # jaw_free: without the lips taking back what the jaw carries)
        controls_face.fap_mapping = {**mapping, "table_scale": (table_scale if scale is None else scale).copy(),
                                     "jaw_follow": np.zeros(FAP_COUNT) if jaw_free else jaw_follow.copy(),
                                     "hold_scale": hold_scale.copy()}
        return FapControls(controls_face, model)

    def refine_job(side: float, todo: list[int]) -> tuple:
        # FAPs `todo` of one batch probed again at `side` with their scales as they stand
        # (a probe at the positive limit reads its half-range column too, to the last bit of
        # the table's interpolation: whether that side's refinement was read before is the
        # threads' timing, which moves the mapping by a rounding error at most)
        return (*_probe_jobs(batches, [(k, side) for k in todo], half)[0], controls_now())

    def refined(job: tuple, skin: np.ndarray) -> list[int]:
        # a refinement's measurement: its FAPs that missed again, at the next scale to try
        side, todo = job[0], job[1]
        again = []
        for k in todo:
            cols = _scale_columns(k, side)
            seen = measured[(k, side)]
            along = moved_along(FAP_FEATURE_POINT[k - 1], k, skin) * np.sign(side)
            seen.append((float(table_scale[k - 1, cols[0]]), along / expected_motion(k, side)))
            step = _next_scale(seen) if _miss(seen[-1][1]) > REFINE_TOLERANCE else None
            if step is not None:
                table_scale[k - 1, cols] = step
                again.append(k)
        return again

    overlap: dict[int, list[float]] = {}  # twin-over-own motion ratios of the last pass (none: 0)
    # every (FAP, side) measured: [(table scale, measured over expected)], for the refinement
    measured: dict[tuple[int, float], list[tuple[float, float]]] = {}
    for pass_index in range(passes):
        last = pass_index == passes - 1
        overlap = {}
        # open_jaw is probed without the lips taking back what it carries (jaw_follow): that
        # is what it measures; the "hold" job probes it with them
        ctl, jaw_alone = controls_now(), controls_now(jaw_free=True)
        follow_asked = jaw_follow.copy()  # what the lips take back in this pass's hold job
        jobs = _probe_jobs(batches, [(k, side) for side in SCALE_COLUMNS for k in faps
                                     if (side == 1.0 and np.any(gain_pos[k - 1]))
                                     or (side == 2.0 and k in FULL_RANGE_FAPS and np.any(gain_pos[k - 1]))
                                     or (side < 0 and FAP_LIMITS[k - 1, 0] < 0 and np.any(gain_neg[k - 1]))], half)
        jobs = [(*job, jaw_alone if JAW_OPEN in job[1] else ctl) for job in jobs]
        if JAW_OPEN in faps and np.any(follow_asked):
            values = np.zeros(FAP_COUNT)
            values[JAW_OPEN - 1] = half[JAW_OPEN - 1]
            jobs.append((1.0, [JAW_OPEN], values, "hold", ctl))
        # Refinement (after the last pass): a FAP whose last correction was large is measured
        # again at its new scale (beside its batch mates that are measured again too); where
        # the skin snaps between two settled states (a pull that stretches edges to the strain
        # limit drags the tissue beside it along), the scale is searched between the largest
        # that fell short and the smallest that overshot, at most REFINE_PASSES times. A
        # batch's refinement starts as soon as its last probe is read, while the pass's other
        # probes still run (a pass at a time left a core idle at the end of each).
        refining: dict = {}  # future -> (job, how many times its FAPs were refined)
        with ThreadPoolExecutor(threads) as pool:
            futures = [pool.submit(settled, job) for job in jobs]
            carried = {}
            for job, future in zip(jobs, futures):
                side, todo, _, kind, _ = job
                skin = future.result()
                if kind == "hold":
                    held = skin
                    continue
                if side == 1.0 and JAW_OPEN in todo:
                    # what open_jaw alone carries the lip points by, to be taken back by their FAPs
                    for k in LIP_FAPS:
                        fdp = FAP_FEATURE_POINT[k - 1]
                        if fdp in probe.fdp and (np.any(gain_pos[k - 1]) or np.any(gain_neg[k - 1])):
                            jaw_follow[k - 1] = moved_along(fdp, k, skin) / (half[JAW_OPEN - 1] * unit[k - 1])
                            carried[k] = jaw_follow[k - 1]
                for k in todo:
                    along = moved_along(FAP_FEATURE_POINT[k - 1], k, skin) * np.sign(side)
                    twin = twin_of.get(k)
                    if twin is not None and FAP_FEATURE_POINT[twin - 1] in probe.fdp and abs(along) > 0:
                        # the twin's point moves with k only inside k's footprint (elsewhere a
                        # batch mate may move it): outside, the two do not overlap
                        tp = FAP_FEATURE_POINT[twin - 1]
                        ratio = 0.0
                        if footprint[k][probe.fdp[tp][0]].all():
                            ratio = float(np.clip(moved_along(tp, twin, skin) * np.sign(side) / along, 0.0, 1.0))
                        overlap.setdefault(k, []).append(ratio)
                    expected = expected_motion(k, side)
                    cols = _scale_columns(k, side)
                    measured.setdefault((k, side), []).append((float(table_scale[k - 1, cols[0]]), along / expected))
                    g = float(np.clip(expected / along, 0.5, 2.0)) if along > 1e-3 * expected else 2.0
                    if last and k not in JAW_FAPS and _miss(along / expected) <= REFINE_TOLERANCE:
                        continue  # near its value at a measured scale: a step more might cross a snap
                    table_scale[k - 1, cols] *= g
                    if k == JAW_OPEN and side == 1.0:
                        jaw_follow *= g  # the jaw carries the lips as far as it opens
                again = [k for k in todo if last and k not in JAW_FAPS
                         and _miss(measured[(k, side)][-1][1]) > REFINE_TOLERANCE]
                if again and REFINE_PASSES:
                    job = refine_job(side, again)
                    refining[pool.submit(settled, job)] = (job, 1)
            while refining:
                done, _ = wait(refining, return_when=FIRST_COMPLETED)
                for future in done:
                    job, times = refining.pop(future)
                    again = refined(job, future.result())
                    if again and times < REFINE_PASSES:
                        job = refine_job(job[0], again)
                        refining[pool.submit(settled, job)] = (job, times + 1)
        if carried and jobs[-1][3] == "hold":
            # the lips' hold against the jaw: what they took back (the jaw's carry less what
            # is left) against what they were asked to (follow_asked), per lip FAP
            for k, carry in carried.items():
                fdp = FAP_FEATURE_POINT[k - 1]
                if abs(follow_asked[k - 1]) < 0.05 or abs(carry) < 0.05:
                    continue
                left = moved_along(fdp, k, held) / (half[JAW_OPEN - 1] * unit[k - 1])
                taken = (carry - left) / follow_asked[k - 1]
                hold_scale[k - 1] *= float(np.clip(1.0 / taken, 0.5, 2.0)) if taken > 0.0 else 2.0

    for (k, side), seen in measured.items():
        if k not in JAW_FAPS and _miss(seen[-1][1]) > REFINE_TOLERANCE:
            # the scale now set was never measured (or was, and missed): the best one that was
            best = min(seen, key=lambda sr: _miss(sr[1]))[0]
            table_scale[k - 1, _scale_columns(k, side)] = best
    if warm_start_usable(start):
        start_scale = np.asarray(start["table_scale"], dtype=np.float64)

        def measure_whole(*tries: list[tuple[int, float, float]]) -> None:
            # each (FAP, side, scale) held alone on the whole skin with that table scale: its
            # measured / expected motion joins seen[(FAP, side)]; the lists of `tries` all at
            # once (a list takes one FAP's side once)
            jobs, done = [], []
            for some in tries:
                trial = table_scale.copy()
                for k, side, scale in some:
                    trial[k - 1, _scale_columns(k, side)] = scale
                controls = controls_now(trial)
                for k, side, scale in some:
                    values = np.zeros(FAP_COUNT)
                    values[k - 1] = side * half[k - 1]
                    jobs.append((side, [k], values, "whole", controls))
                    done.append((k, side, scale))
            if not jobs:
                return
            with ThreadPoolExecutor(threads) as pool:
                skins = list(pool.map(settled, jobs))
            for (k, side, scale), skin in zip(done, skins):
                along = moved_along(FAP_FEATURE_POINT[k - 1], k, skin) * np.sign(side)
                seen[(k, side)].append((scale, along / expected_motion(k, side)))

        moved = [(k, side) for (k, side) in measured if k in LIP_MARGIN_FAPS
                 and abs(table_scale[k - 1, _scale_columns(k, side)[0]]
                         / start_scale[k - 1, _scale_columns(k, side)[0]] - 1.0) > WHOLE_CHECK_SHIFT]
        seen = {key: [] for key in moved}  # (k, side) -> [(scale, ratio on the whole skin)]
        measure_whole(*([(k, side, float(scales[k - 1, _scale_columns(k, side)[0]])) for k, side in moved]
                        for scales in (table_scale, start_scale)))
        # one more try where neither was near: the next scale those two suggest (nearest last)
        nearest_last = {key: sorted(s_r, key=lambda sr: _miss(sr[1]), reverse=True) for key, s_r in seen.items()}
        measure_whole([(k, side, scale) for (k, side), s_r in nearest_last.items()
                       if _miss(s_r[-1][1]) > REFINE_TOLERANCE and (scale := _next_scale(s_r)) is not None])
        for (k, side), s_r in seen.items():
            table_scale[k - 1, _scale_columns(k, side)] = min(s_r, key=lambda sr: _miss(sr[1]))[0]
    mapping["table_scale"] = table_scale
    mapping["pair_overlap"] = pair_overlap_of(overlap)
    out = copy.copy(face)
    out.fap_mapping = mapping
    # tables baked from the head's simulation under another mapping move it otherwise (a
    # head loaded with a mapping of an older format is calibrated again): baked again on demand
    out.face_def_tables = [t for t in face.face_def_tables if t.source != "physics"]
    return out


def _scale_columns(k: int, side: float) -> list[int]:
    """The table_scale columns of FAP k that a probe at amplitude `side` sets (SCALE_COLUMNS)."""
    if side == 1.0 and k in FULL_RANGE_FAPS:
        return [3]
    return SCALE_COLUMNS[side]


def _probe_jobs(batches: list[list[int]], todo: list[tuple[int, float]], half: np.ndarray) -> list[tuple]:
    """Settle jobs (side, FAPs, values (68,), "probe") for the (FAP, side) pairs `todo`:
    one per batch and side holding those of its FAPs at side x half range (side: 1, -1, or
    2 for the positive limit)."""
    jobs = []
    for side in SCALE_COLUMNS:
        for batch in batches:
            faps = [k for k in batch if (k, side) in todo]
            if faps:
                values = np.zeros(FAP_COUNT)
                values[np.array(faps) - 1] = side * half[np.array(faps) - 1]
                jobs.append((side, faps, values, "probe"))
    return jobs


def _miss(ratio: float) -> float:
    """How far a measured / expected motion ratio is off, as a share (0.1: 10 % short or
    over; a motion the wrong way or none counts as far off)."""
    return float(np.exp(abs(np.log(max(ratio, 1e-3)))) - 1.0)


def _next_scale(seen: list[tuple[float, float]]) -> float | None:
    """The next table scale to try from the (scale, measured / expected) pairs seen so far
    (the motion grows with the scale): between the largest scale that fell short and the
    smallest that overshot, where both are known (interpolated in logs, kept off the ends
    so the bracket shrinks), else the last scale times expected / measured (at most 2x);
    None where the motion did not grow with the scale (a smaller scale overshot a larger
    one): no bracket to search, the best scale seen is kept."""
    scale, ratio = seen[-1]
    short = [sr for sr in seen if sr[1] < 1.0]
    over = [sr for sr in seen if sr[1] > 1.0]
    if not short or not over:
        return scale * float(np.clip(1.0 / max(ratio, 1e-6), 0.5, 2.0))
    (s0, r0), (s1, r1) = max(short), min(over)
    if s1 <= s0:
        return None
    t = np.log(1.0 / max(r0, 1e-6)) / np.log(r1 / max(r0, 1e-6))
    t = float(np.clip(t, 0.25, 0.75))
    return float(np.exp(np.log(s0) + t * (np.log(s1) - np.log(s0))))


def pair_overlap_of(ratios: dict[int, list[float]]) -> np.ndarray:
    """(68,) 0..1: per LIP_PAIRS FAP, the mean of the twin-over-own motion ratios measured
    for either FAP of its pair (0 where none was)."""
    out = np.zeros(FAP_COUNT)
    for pair in LIP_PAIRS:
        r = ratios.get(pair[0], []) + ratios.get(pair[1], [])
        if r:
            out[[pair[0] - 1, pair[1] - 1]] = float(np.clip(np.mean(r), 0.0, 1.0))
    return out


def warm_start_usable(mapping: dict | None) -> bool:
    """Whether `mapping`'s table scales can start a calibration: made for this solver
    (FORMAT_VERSION), one finite positive row of 5 scales for each of the 68 FAPs."""
    if not mapping or any(k not in mapping for k in ("table_scale", "layout", "jaw_follow", "hold_scale")):
        return False
    scale = np.asarray(mapping["table_scale"])
    layout = np.asarray(mapping["layout"]).ravel()
    return (layout.size >= 4 and int(layout[3]) == FORMAT_VERSION and scale.shape == (FAP_COUNT, 5)
            and bool(np.all(np.isfinite(scale))) and bool(np.all(scale > 0)))


def _disjoint_batches(face, model, faps, responses, gain_pos, gain_neg, unit
                      ) -> tuple[list[list[int]], dict[int, np.ndarray]]:
    """FAPs grouped so that no two in a group move the same skin (footprint + 2 rings), and
    each FAP's footprint ((V,) bool skin vertices)."""
    A = adjacency(np.asarray(face.skin_faces), len(face.skin_vertices))
    footprint = {}
    for k in faps:
        g = (np.abs(gain_pos[k - 1]) + np.abs(gain_neg[k - 1])) / np.maximum(unit[k - 1], 1e-12)
        u = sum(g[c] * np.abs(responses[c]) for c in np.flatnonzero(g))
        mag = np.linalg.norm(u, axis=1)
        footprint[k] = dilate(mag > 0.02 * mag.max(), A, 2)
    batches: list[list[int]] = []
    for k in faps:
        for b in batches:
            if k not in JAW_FAPS and not any(o in JAW_FAPS for o in b) and k not in ALONE_FAPS \
                    and not any(o in ALONE_FAPS for o in b) \
                    and not any(np.any(footprint[k] & footprint[o]) for o in b):
                b.append(k)
                break
        else:
            batches.append([k])
    return batches, footprint


def settle_scratch(model) -> tuple:
    """(state, control, rest state) for `settle` to reuse across calls."""
    return model.state(), model.control(), model.state()


def settle(model, solver, controls, values: np.ndarray, rig, frames: int = 40, fps: float = 25.0,
           tolerance: float = 2e-6, scratch: tuple | None = None, watch: tuple | None = None) -> np.ndarray:
    """(V, 3) skin in the head frame after holding FAP `values` until it stops moving.

    scratch: (state, control, rest state) to reuse, from `settle_scratch(model)`: the
    solver's launches are recorded for the arrays they run on, so new ones for every call
    cost more than the steps (17 s of a calibration's recording for 156 calls).
    watch: the points a probe measures, (W, 3) int skin vertices, (W, 3) barycentric
    weights, (W, 3) unit directions; from SETTLE_MIN_FRAMES on, the skin counts as settled
    once each point's motion along its direction changed by less than SETTLE_TOLERANCE of
    itself over each of two frames running (the rest of the skin may still creep; skin
    that is not simulated is on its hold from the start and is not watched)."""
    if scratch is None:
        state, control = model.state(), model.control()
    else:
        state, control, rest = scratch
        state.assign(rest)
    activation, jaw = controls.controls(values)
    R, t = np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3))
    T = rig.jaw(*jaw)
    R[1], t[1] = T[:3, :3], T[:3, 3]
    control.set(muscle_activation=activation, bone_rotation=R, bone_translation=t)
    prev = state.particle_q.numpy().copy()
    along = None
    still = 0  # frames running in which the watched points moved less than SETTLE_TOLERANCE
    particles = None
    if watch is not None and np.any(model.skin_particle[watch[0]] >= 0):
        # skin that is not simulated sits on its hold from the first frame: only the
        # simulated corners of a point's triangle can still move it
        particles = np.maximum(model.skin_particle[watch[0]], 0)
        weights = np.where(model.skin_particle[watch[0]] >= 0, watch[1], 0.0)
        start = np.einsum("wk,wkj,wj->w", weights, prev[particles], watch[2])
    for i in range(frames):
        solver.step(model, state, control, 1.0 / fps, state)
        q = state.particle_q.numpy().copy()  # on the CPU .numpy() is a view of the state
        if i > 3 and np.abs(q - prev).max() < tolerance:
            break
        prev = q
        if particles is not None:
            now = np.einsum("wk,wkj,wj->w", weights, q[particles], watch[2]) - start
            calm = along is not None and np.all(np.abs(now - along) < SETTLE_TOLERANCE * np.maximum(np.abs(now), 1e-4))
            still = still + 1 if calm else 0
            if i + 1 >= SETTLE_MIN_FRAMES and still >= 2:
                break
            along = now
    return skin_positions(model, state.particle_q.numpy().astype(np.float64), R, t)
