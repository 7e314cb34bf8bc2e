"""Build a SkinModel from any FaceModel: the 3-layer skin, springs, anchors, muscle
influences and bone distance grids (all setup work; nothing here runs per frame).

Layers: the epidermis is the skin mesh; the middle and deepest layers are the skin moved
inward along the vertex normals by skin_thickness x layer fraction (default fractions
[0, 0.5, 1], `layer_params["layer_depth_fractions"]`). Springs join the ends of every
mesh edge within each layer, each vertex to itself in the next layer, and crosswise each
edge's ends to the other end in the next layer. Muscles act on the middle layer; pull
fields on the two upper layers.

Holds: every particle is anchored by a zero-length spring to its hold, its rest place
carried by the skull, the mandible or a blend of both (`jaw_weights`: a harmonic blend
between skin clearly over one bone, lower lip and chin on the jaw, upper lip on the
skull, the neck off the jaw, so that the skin between skull and jaw stretches smoothly
over a band): the deepest layer stiffly, the upper layers weakly (tethers).

Only skin near a muscle or a pull field is simulated (`active_rings` 3 edge rings around
it, plus one ring that sits on its hold: 3,000 of the generic head's 9,000 vertices); the
rest (scalp, neck, the inside of the mouth, the ears) moves with its hold
(`skin_positions`; 2,100 of those vertices follow the jaw in part). The ears' FAPs move
them directly (fae.animate.ears).

Parameters (keys of `layer_params`, else these defaults): stiffness per unit mass kappa
(1/s^2) `kappa_epidermis` 600, `kappa_middle` 300, `kappa_deep` 300, `kappa_vertical`
1000, `kappa_cross` 400, `kappa_anchor` 10000 (deepest layer to its hold), `kappa_tether`
500 (upper layers to theirs); `drag` 70 1/s, of which `drag_carried_skin` 0.8 is taken
relative to the hold as a bone moves it, `drag_carried` 0.3 on the lips (`carried_share`,
fae.sim.integrate: a jaw opened in one frame left the chin at 31 % of its drop in that
frame with the whole drag against the motion, 66 % now); `density` 1100 kg/m^3;
(a pull field may lower the drag of the skin it pulls: `PullField.drag`, the eyelids'
30, fae.animate.calibrate);
`muscle_acceleration` 50 m/s^2 (force per unit activation and weight, per kg);
`jaw_reach` 15 mm, `jaw_sure` 0.5, `jaw_corner_blend` 0.2, `jaw_blend_rings` 4 (see
`jaw_weights`). How fast the skin follows a muscle is set by the drag against the
stiffness that resists large deformations (tethers and cross springs: a muscle's step
reaches 90 % of its pull in 3-4 frames at 25 fps, about as with springs four times as stiff
and five explicit substeps); the stable substep by the stiffest, the in-plane springs
(with the drag and anchors implicit, fae.sim.solver: 20.7 ms, two substeps per 25 fps
frame). Equilibria depend on stiffness ratios only; calibration sets the amplitudes.
Layer order: an epidermis particle stays at least `layer_min_height` 0.1 of its rest
height above its vertex in the middle layer (0.25, and the middle layer over the deepest
too, held the lower lip's raise to 0.72 of its FAP) (fae.sim.integrate). Contact:
penetrations of skin the bone moved onto deeper than `contact_depth` 4 mm are left to
the springs (see fae.sim.collision). Folds (fae.sim.folds): triangles of the two upper
layers below `fold_min_area` 0.5 of their rest area (in their rest plane) are restored,
epidermis particles whose Laplacian offset strays more than `crease_tolerance` 0.2 x their
mean edge are moved back, epidermis edges where the skin is seen are kept between
`strain_min` 0.4 and `strain_max` 1.8 x their rest length, and lip particles facing each
other within `LIP_PAIR_REACH` 6 mm stay in order (each with up to `LIP_PAIR_NEIGHBOURS` 6
of the other lip's; so does each upper lid's lining within `lip_reach` 3 mm
of its front's margin: it sinks no further below the margin than at rest, nor rises more
than `LID_MARGIN_SLACK` over its rest height; and an upper lid's skin near its margin stays
above the lower lid's margin, `LID_CONTACT_BAND`), in up to
`fold_passes` 4 passes per substep. (Setting in at 0.5 of the rest area and 0.2 of an
edge, over four passes, each head calibrated again: the nine xface streams' triangles ever
folded, shipped head 100 -> 52, the three busts' 223 / 287 / 389 -> 151 / 208 / 257; at 0.3,
0.25 and three passes before. 0.6 of the area folded more lids, a tolerance of 0.15
stretched the wreath's lip corners to 5x, five passes cost a fifth of the frame rate.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve
import warp as wp
from scipy.spatial import cKDTree

from fae.io.facemodel import FaceModel
from fae.mesh import adjacency_from_edges, vertex_areas, vertex_normals
from fae.mesh import edges as mesh_edges
from fae.sim.folds import CreaseVertex, GuardedTriangle, LipPair, crease_vertices, guarded_triangles, lid_pairs, lip_pairs
from fae.sim.model import (BONE_COUNT, BONE_NAMES, LAYER_COUNT, MUSCLE_FIELD, MUSCLE_LINEAR, MUSCLE_SPHINCTER,
                           SkinModel)
from fae.sim.sdf import sample_grid, signed_distance_grid
from fae.sim.solver import stable_substep

# skin seen only through the lips: its strain is not limited (it stretches as the mouth opens)
HIDDEN_REGIONS = ("mouth_cavity",)
LIP_REGIONS = ("lip_upper", "lip_lower")
LIP_CARRY_RINGS = 4  # edge rings over which the lips' carried drag blends into the skin's

DEFAULTS = {
    "layer_depth_fractions": [0.0, 0.5, 1.0],
    "kappa_epidermis": 600.0,
    "kappa_middle": 300.0,
    "kappa_deep": 300.0,
    "kappa_vertical": 1000.0,
    "kappa_cross": 400.0,
    "kappa_anchor": 10000.0,
    "kappa_tether": 500.0,
    "drag": 70.0,
    "drag_carried": 0.3,
    "drag_carried_skin": 0.8,
    "density": 1100.0,
    "muscle_acceleration": 50.0,
    "active_rings": 3,
    "cfl": 0.9,
    "sdf_cell": 0.003,
    "contact_depth": 0.004,
    "layer_min_height": 0.1,
    "jaw_reach": 0.015,
    "jaw_sure": 0.5,
    "jaw_corner_blend": 0.2,
    "jaw_blend_rings": 4,
    "fold_min_area": 0.5,
    "fold_passes": 4,
    "crease_tolerance": 0.2,
    "strain_max": 1.8,
    "strain_min": 0.4,
    "lip_reach": 0.003,
}


@dataclass
class PullField:
    """A directional pull field (a pseudo-muscle of kind MUSCLE_FIELD).

    name        unique name
    direction   (3,) unit vector in the head frame
    skin_weight (V,) float64 in [0, 1], weight of each skin vertex (zero: untouched)
    drag        1/s: the drag of the skin it pulls (all three layers under a vertex,
                though it pulls the upper two), blended from the skin's by the weight
                (None: the skin's `drag`); lower follows the pull sooner
    """

    name: str
    direction: np.ndarray
    skin_weight: np.ndarray
    drag: float | None = None


# what a head's layer_params may set: counts at most MAX_RINGS, other numbers finite, >= 0
# and at most PARAM_SPAN x their default (past that, a step takes for ever or blows up),
# these few at least their default / PARAM_SPAN, the contact grid no finer than MIN_SDF_CELL
# metres, cfl at most 1
COUNT_PARAMS = ("active_rings", "jaw_blend_rings", "fold_passes")
MAX_RINGS = 50
PARAM_SPAN = 1000.0
POSITIVE_PARAMS = ("density", "cfl", "sdf_cell")
FRACTION_PARAMS = ("cfl", "drag_carried", "drag_carried_skin")  # at most 1
MIN_SDF_CELL = 0.0005


def checked_params(p: dict) -> dict:
    """`p` (DEFAULTS' keys) if every value is usable; ValueError naming the first that is not."""
    for key, value in p.items():
        where = f"layer_params.{key}"
        if key == "layer_depth_fractions":
            try:
                fr = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                fr = np.zeros(0)
            if fr.shape != (LAYER_COUNT,) or fr[0] != 0.0 or not np.all(np.diff(fr) > 0) or fr[-1] > PARAM_SPAN:
                raise ValueError(f"{where}: expected [0, f1, f2] increasing, got {value!r:.80}")
            continue
        if key not in DEFAULTS:
            continue
        if key in COUNT_PARAMS:  # 3.0 as JSON writes a float is 3
            whole = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) \
                and math.isfinite(value) and float(value).is_integer()
            if not whole or not 0 <= value <= MAX_RINGS:
                raise ValueError(f"{where}: expected a whole number 0..{MAX_RINGS}, got {value!r}")
            continue
        top = 1.0 if key in FRACTION_PARAMS else PARAM_SPAN * DEFAULTS[key]
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        # a positive one far below its default multiplies the substeps (cfl 1e-9: a frame took minutes)
        low = MIN_SDF_CELL if key == "sdf_cell" else DEFAULTS[key] / PARAM_SPAN if key in POSITIVE_PARAMS else 0.0
        if isinstance(value, bool) or not low <= number <= top:
            raise ValueError(f"{where}: expected a number in [{low:g}, {top:g}], got {value!r}")
    return p


def carried_share(face: FaceModel, A: sp.csr_matrix, params: dict) -> np.ndarray:
    """(V,) float64 in [0, 1]: the share of each skin vertex's drag taken relative to its
    moving hold (fae.sim.integrate): `drag_carried` on the lips, `drag_carried_skin`
    elsewhere, blended over LIP_CARRY_RINGS edge rings around the lips (A: the skin's
    vertex adjacency). The more of its drag is carried, the sooner skin keeps up with the
    bone under it; but a lip's FAP takes back part of the jaw's carry through muscles the
    drag still holds back, and the lips carried as much as the chin ran past their place as
    the jaw opened (2.2x with the whole drag carried, 1.3x with 0.6, 1.25x at 60 frames/s
    with 0.4; 1.07x at most with 0.3, at 25 to 100 frames/s)."""
    lip_share, skin_share = float(params["drag_carried"]), float(params["drag_carried_skin"])
    names = list(face.region_names)
    lips = np.isin(np.asarray(face.skin_region), [names.index(r) for r in LIP_REGIONS if r in names])
    share = np.where(lips, lip_share, skin_share)
    reached = lips
    for k in range(1, LIP_CARRY_RINGS + 1):
        grown = dilate(reached, A, 1)
        share[grown & ~reached] = lip_share + (skin_share - lip_share) * k / (LIP_CARRY_RINGS + 1)
        reached = grown
    return share


def dilate(mask: np.ndarray, A: sp.csr_matrix, rings: int) -> np.ndarray:
    """(n,) bool: `mask` grown by `rings` edge rings over adjacency A."""
    m = mask.copy()
    for _ in range(rings):
        grown = m | (A @ m.astype(np.float64) > 0)
        if np.array_equal(grown, m):  # nothing more to reach
            break
        m = grown
    return m


def max_stiffness_rate(n: int, pairs: np.ndarray, stiffness: np.ndarray, mass: np.ndarray,
                       movable: np.ndarray) -> float:
    """1/s^2: an upper bound of the largest eigenvalue of M^-1 K of the spring network.

    A spring's stiffness block k (n n^T + (1 - r/l)(I - n n^T)) is at most k I whenever it
    is not compressed below its rest length r (compressed, the transverse term is
    negative), so the weighted graph Laplacian (spring stiffness k_ij) bounds M^-1 K in
    every configuration. Its largest eigenvalue, over the movable particles (Lanczos, scipy
    eigsh), is typically 0.55 of the Gershgorin row-sum bound; 2% is added for the solver's
    tolerance. pairs (S, 2) int, stiffness (S,) N/m, mass (n,) kg, movable (n,) bool.
    """
    from scipy.sparse.linalg import ArpackNoConvergence, eigsh

    keep = np.flatnonzero(movable)
    if len(keep) == 0:
        return 1.0
    i, j = pairs[:, 0], pairs[:, 1]
    L = sp.coo_matrix((np.concatenate([stiffness, stiffness, -stiffness, -stiffness]),
                       (np.concatenate([i, j, i, j]), np.concatenate([i, j, j, i]))), shape=(n, n)).tocsr()
    w = sp.diags(1.0 / np.sqrt(mass[keep]))
    B = (w @ L[keep][:, keep] @ w).tocsr()
    gershgorin = float(np.max(np.abs(B).sum(axis=1)))
    if len(keep) < 3:
        return gershgorin
    try:
        lam = float(eigsh(B, k=1, which="LA", tol=1e-6, v0=np.ones(len(keep)), return_eigenvectors=False)[0])
    except ArpackNoConvergence:
        return gershgorin
    return min(1.02 * lam, gershgorin)


def jaw_weights(face: FaceModel, deep: np.ndarray, A: sp.csr_matrix, params: dict) -> np.ndarray:
    """(V,) float in [0, 1]: how much the hold of each skin vertex follows the mandible.

    deep (V, 3) metres: the deepest layer; A (V, V) the skin's vertex adjacency. Skin whose
    deepest layer lies clearly nearer one bone (less than `jaw_sure` times its distance to
    the other; skull with upper teeth, mandible with lower teeth; and for the mandible within
    `jaw_reach` of it) is held by that bone alone,
    as are the lower lip and chin (by the jaw) and the upper lip (by the skull), where the
    head has those regions (both lips lie over both rows of teeth), while the mouth's lining
    (its region) is held by neither alone: it stretches from lip to lip as the mouth opens,
    not just over the thin band between the teeth; skin farther than three times `jaw_reach`
    from the mandible is held by the skull (the neck hangs from the skull and the body, not
    the jaw).
    Everywhere else, the mouth's corners included (within `jaw_corner_blend` times the mouth
    width of feature points 2.4 and 2.5, where upper and lower lip meet) and `jaw_blend_rings`
    edge rings around any seam between skin held by one bone and by the other, the weight is the
    harmonic interpolation of these (Laplace's equation over the skin's edges, weighted by
    inverse length): the skin between skull and jaw stretches smoothly over the whole band
    instead of tearing along a line. Without a mandible, 0 everywhere.
    """
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    meshes = [_bone_mesh(face, b) for b in BONE_NAMES]
    if len(meshes[1][0]) == 0:
        return np.zeros(len(V))
    dist = [cKDTree(_surface_samples(bv, bf)).query(deep)[0] if len(bv) else np.full(len(deep), np.inf)
            for bv, bf in meshes]
    sure, reach = float(params["jaw_sure"]), float(params["jaw_reach"])
    w = np.full(len(V), np.nan)
    w[(dist[1] < sure * dist[0]) & (dist[1] < reach)] = 1.0
    w[(dist[0] < sure * dist[1]) | (dist[1] > 3.0 * reach)] = 0.0
    names = list(face.region_names)
    region = np.asarray(face.skin_region)
    for name, value in (("lip_lower", 1.0), ("chin", 1.0), ("lip_upper", 0.0), ("mouth_cavity", np.nan)):
        if name in names:
            w[region == names.index(name)] = value
    corners = [face.surface_point_position(face.feature_points[c]) for c in ("2.4", "2.5")
               if c in face.feature_points and face.feature_points[c].part == "skin"]
    if len(corners) == 2:
        radius = float(params["jaw_corner_blend"]) * np.linalg.norm(corners[0] - corners[1])
        for c in corners:
            w[np.linalg.norm(V - c, axis=1) < radius] = np.nan
    # where skin held by the skull comes near skin held by the jaw (the skin's depth jumps
    # there, below the ears), `jaw_blend_rings` edge rings on either side are left to blend
    rings = int(params["jaw_blend_rings"])
    ones, zeros = w == 1.0, w == 0.0
    w[(ones & dilate(zeros, A, rings)) | (zeros & dilate(ones, A, rings))] = np.nan
    free = np.isnan(w)
    if not np.any(free):
        return w
    # Laplace's equation for the free vertices, with a faint pull towards the nearer bone so
    # that a free patch touching no held skin still has one solution
    i, j = sp.triu(A, k=1).nonzero()
    g = 1.0 / np.maximum(np.linalg.norm(V[i] - V[j], axis=1), 1e-6)
    W = sp.coo_matrix((np.concatenate([g, g]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                      shape=(len(V), len(V))).tocsr()
    degree = np.asarray(W.sum(axis=1)).ravel()
    nearer = np.where(dist[1] < dist[0], 1.0, 0.0)
    eps = 1e-4 * degree[free]
    held = np.where(free, 0.0, w)
    L = (sp.diags(degree[free] + eps) - W[free][:, free]).tocsc()
    w[free] = spsolve(L, W[free] @ held + eps * nearer[free])
    return np.clip(w, 0.0, 1.0)


def _bone_mesh(face: FaceModel, bone: str) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, off = [], [], 0
    for part in face.parts.values():
        if part.bone == bone and part.faces is not None and len(part.faces):
            vs.append(np.asarray(part.vertices, dtype=np.float64))
            fs.append(np.asarray(part.faces, dtype=np.int64) + off)
            off += len(part.vertices)
    if not vs:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(vs), np.concatenate(fs)


# The eyeballs are spheres the skin slides over: a closing eyelid passes in front of the
# eye, not through it (a pull field moves it straight down; the cornea is in its way).
# A particle within EYE_REACH of an eyeball at rest keeps EYE_CLEARANCE from it, less where
# it lies closer at rest (the lids' lining, 0.7 mm off the generic head's eyes: it keeps
# all but EYE_SLACK of that), so that flat lid triangles spanning the curved eye do not cut
# into it between their corners.
EYE_PARTS = ("eye_l", "eye_r")
EYE_REACH = 0.006
EYE_CLEARANCE = 0.001
EYE_SLACK = 0.0002
# Round each eye, the skin of the lower lids and cheeks (EYE_BAND_REGIONS) within
# EYE_BAND_REACH of the eyeball keeps its layering: the skin a viewer sees keeps
# EYE_OUTER_KEEP of its rest distance from the eyeball, and the skin hidden behind the lid
# (its lining) goes no farther out than its rest distance + EYE_LINING_SLACK. A rising
# cheek rolled the lower lid's margin inward and its outer skin passed behind the lining,
# whose dark back then showed below the eye.
EYE_BAND_REACH = 0.012
EYE_OUTER_KEEP = 0.8
EYE_LINING_SLACK = 0.001
# (not the upper lids: opening wide, a lid folds its skin and lining up into its crease,
# and held in such a band they were squeezed to a tenth of their length)
EYE_BAND_REGIONS = ("eyelid_lower_l", "eyelid_lower_r", "cheek_l", "cheek_r")
UPPER_LID_REGIONS = ("eyelid_upper_l", "eyelid_upper_r")
# each eye's upper and lower lid, in the order of EYE_PARTS; the upper lid's skin within
# LID_CONTACT_BAND above its margin (metres) stays above the lower lid's margin
# (fae.sim.folds.lid_pairs): the margin's front and lining edges alone let the skin between
# them through. Not within LID_CORNER_SHARE of the lower margin's width from either corner,
# where the lids meet at rest. A margin: lid_margin_vertices (MARGIN_ENVELOPE_DX and _DY,
# metres: how near across the face, and how much nearer the eye's opening, a vertex must
# lie to drop another)
LID_CONTACT_BAND = 0.003
LID_CORNER_SHARE = 0.1
MARGIN_ENVELOPE_DX, MARGIN_ENVELOPE_DY = 0.002, 0.0005
LID_REGION_PAIRS = (("eyelid_upper_l", "eyelid_lower_l"), ("eyelid_upper_r", "eyelid_lower_r"))
# An upper lid is a thin fold, its front over its lining. As a blink opened, the front's
# crease came back into the socket ahead of the lining and the margin rolled out: for a
# frame the lining's dark back showed over the iris (1,200 of 45,000 rays from the front
# met a back face). So the skin a viewer sees of an upper lid keeps at least
# EYE_UPPER_FRONT_KEEP from the eyeball (or its rest distance less EYE_SLACK, where less),
# and along the margin the lining rises no more than LID_MARGIN_SLACK above its rest height
# over the front (fae.sim.folds.LipPair): 40 such rays (the front's keep alone left 66, the
# margin's alone 600; the lining also held near the eyeball, as the lower lids' is, left
# 26, but a lid opened wide stretched its margin 3.7x against it).
EYE_UPPER_FRONT_KEEP = 0.002
LID_MARGIN_SLACK = 0.0005
# each lip particle is kept above (below) up to LIP_PAIR_NEIGHBOURS of the other lip's within
# LIP_PAIR_REACH at rest: the slit's walls are meshed with vertices up to 10 mm apart, and
# paired with the nearest within 3 mm alone, a pressed lower lip's vertex rose through the
# upper wall's triangle between its corners (expressions.fap's anger: the lips crossed in 35
# frames, 30 now; xface_beg 3 -> 0, xface_hate 2 -> 0)
LIP_PAIR_REACH = 0.006
LIP_PAIR_NEIGHBOURS = 6
# and a lip particle that lay above (below) its partner at rest stays LIP_CLEARANCE above
# (below) it, or as far as it lay: the slit's walls slope between their particles, and
# pressed level with its partners, a lower lip's particle still poked 0.2 mm through the
# upper lip's wall (the shipped head's anger in expressions.fap: 11 lip edges through it in
# 33 frames; none with 0.3 mm, the lips still meet in a line)
LIP_CLEARANCE = 0.0003
# An adapted head's upper lid can stand off its eyeball: fitted to a bust's sculpted eye, the
# lid's margin and lining lay 5-10 mm in front of the eyeball placed in its socket. Such
# lining (beyond LINING_STANDOFF; the generic head's lies within 3.5 mm) has no eyeball to
# slide on, and as a blink reopened it rolled out through the front (on Demosthenes 139 mm^2
# of it seen by its back). It goes no farther from the eye's centre than at rest, and the
# front over it keeps at least LID_FRONT_OVER_LINING beyond that lining's rest distance (its
# own rest distance less EYE_SLACK, where less).
LINING_STANDOFF = 0.004
LID_FRONT_OVER_LINING = 0.0012


def lid_margin_vertices(face: FaceModel, region_name: str, eye_name: str,
                        normals: np.ndarray | None = None) -> np.ndarray:
    """(M,) int: skin vertices of lid region `region_name` along its margin, sorted by x;
    empty when the head lacks the region or eyeball part `eye_name`. normals (V, 3): the
    skin's vertex normals, when at hand.

    The margin is the edge of the lid's front (skin whose normal faces away from the
    eyeball's centre) nearest the eye's opening: on an adapted head the lid can stand
    several millimetres off the eyeball, so nearness to it does not tell front from lining.
    Of the front's vertices those nearest the opening are kept: a vertex goes when another
    within MARGIN_ENVELOPE_DX across the face lies more than MARGIN_ENVELOPE_DY nearer the
    opening. That also drops vertices where the margin runs steeply near the corners (the
    shipped head's lower margin keeps no point over its outer 6 mm): a line between the
    points kept runs up to 1 mm inside the opening there, so a lid held to it stops early."""
    names = list(face.region_names)
    sphere = eyeball_sphere(face, eye_name)
    if region_name not in names or sphere is None:
        return np.zeros(0, dtype=np.int64)
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    N = vertex_normals(V, np.asarray(face.skin_faces)) if normals is None else normals
    lid = np.asarray(face.skin_region) == names.index(region_name)
    rim = np.flatnonzero(lid & (np.einsum("ij,ij->i", N, V - sphere[0]) > 0.0))
    away = V[rim, 1] if "upper" in region_name else -V[rim, 1]  # from the opening
    near = np.abs(V[rim, 0][:, None] - V[rim, 0][None, :]) < MARGIN_ENVELOPE_DX
    deep = np.any(near & (away[:, None] - away[None, :] > MARGIN_ENVELOPE_DY), axis=1)
    rim = rim[~deep]
    return rim[np.argsort(V[rim, 0], kind="stable")]


def eyeball_sphere(face: FaceModel, name: str) -> tuple[np.ndarray, float] | None:
    """(centre (3,), radius) metres of the eyeball part `name` at rest: its vertices' mean
    and their mean distance from it; None when the head has no such part."""
    part = face.parts.get(name)
    if part is None or part.vertices is None or len(part.vertices) < 4:
        return None
    E = np.asarray(part.vertices, dtype=np.float64)
    centre = E.mean(axis=0)
    return centre, float(np.linalg.norm(E - centre, axis=1).mean())


def eye_spheres(face: FaceModel, q: np.ndarray, candidates: np.ndarray, outer: np.ndarray | None = None,
                lining: np.ndarray | None = None, front: np.ndarray | None = None,
                upper_lining: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P, 4), (P,): for each particle at rest q (P, 3) among `candidates` (P,) bool within
    EYE_REACH of an eyeball (eyeball_sphere), that eyeball's centre and the radius it keeps
    outside of; then within EYE_BAND_REACH, the particles of `outer` (P,) bool keep at least
    EYE_OUTER_KEEP of their rest distance from it, those of `front` (an upper lid's) at least
    EYE_UPPER_FRONT_KEEP (their rest distance less EYE_SLACK where that is less), and those of
    `lining` go no farther than their rest distance + EYE_LINING_SLACK (the second array; 0:
    no limit). Those of `upper_lining` (P,) bool beyond LINING_STANDOFF go no farther than
    their rest distance, and a front particle whose nearest such particle lies beyond
    LINING_STANDOFF keeps LID_FRONT_OVER_LINING beyond it. Zeros elsewhere."""
    from scipy.spatial import cKDTree

    out = np.zeros((len(q), 4))
    far = np.zeros(len(q))
    best = np.full(len(q), np.inf)
    outer = np.zeros(len(q), dtype=bool) if outer is None else outer
    lining = np.zeros(len(q), dtype=bool) if lining is None else lining
    front = np.zeros(len(q), dtype=bool) if front is None else front
    upper_lining = np.zeros(len(q), dtype=bool) if upper_lining is None else upper_lining
    for name in EYE_PARTS:
        sphere = eyeball_sphere(face, name)
        if sphere is None:
            continue
        centre, radius = sphere
        gap = np.linalg.norm(q - centre, axis=1) - radius
        band = candidates & (gap < EYE_BAND_REACH) & (gap < best)
        use = band & (gap > EYE_SLACK) & (gap < EYE_REACH)
        out[band, :3] = centre
        out[band, 3] = 0.0
        out[use, 3] = radius + np.minimum(gap[use] - EYE_SLACK, EYE_CLEARANCE)
        keep = band & outer & (gap > EYE_SLACK)
        out[keep, 3] = np.maximum(out[keep, 3], radius + EYE_OUTER_KEEP * gap[keep])
        keep = band & front & (gap > EYE_SLACK)
        over = EYE_UPPER_FRONT_KEEP
        behind = np.flatnonzero(band & upper_lining)
        if len(behind) and keep.any():  # the lining nearest each front particle, where off the eyeball
            g = gap[behind[cKDTree(q[behind]).query(q[keep])[1]]]
            over = np.where(g >= LINING_STANDOFF, g + LID_FRONT_OVER_LINING, EYE_UPPER_FRONT_KEEP)
        out[keep, 3] = np.maximum(out[keep, 3], radius + np.minimum(gap[keep] - EYE_SLACK, over))
        far[band] = np.where(lining[band], radius + np.maximum(gap[band], 0.0) + EYE_LINING_SLACK, 0.0)
        off = band & upper_lining & (gap >= LINING_STANDOFF)
        far[off] = radius + gap[off]
        best[band] = gap[band]
    return out, far


def _surface_samples(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Vertices, triangle centroids and edge midpoints: points to find the nearer bone."""
    if len(F) == 0:
        return V
    return np.concatenate([V, V[F].mean(axis=1), 0.5 * (V[F[:, 0]] + V[F[:, 1]])])


def _muscle_weights(face: FaceModel, points: np.ndarray) -> list[tuple[dict, np.ndarray]]:
    """Per muscle: (arrays of the muscle, (V,) weight at skin rest `points`)."""
    regions = np.asarray(face.skin_region)
    out = []
    for m in face.muscles:
        allowed = np.ones(len(points), dtype=bool)
        if m.regions:
            ids = [face.region_names.index(r) for r in m.regions if r in face.region_names]
            allowed = np.isin(regions, ids)
        if m.kind == "linear":
            if m.insertion is None:
                raise ValueError(f"muscle {m.name!r}: a linear muscle needs an insertion point")
            a = face.surface_point_position(m.attachment)
            ins = face.surface_point_position(m.insertion)
            axis = ins - a
            d = points - a
            dist = np.linalg.norm(d, axis=1)
            cosang = (d @ axis) / np.maximum(dist * np.linalg.norm(axis), 1e-12)
            ang = np.arccos(np.clip(cosang, -1.0, 1.0))
            zone = max(float(m.zone_angle), 1e-6)
            w_ang = np.where(ang < zone, np.cos(0.5 * np.pi * ang / zone), 0.0)
            rs, rf = float(m.fall_start), float(m.fall_end)
            if not rf > rs > 0:
                raise ValueError(f"muscle {m.name!r}: expected 0 < fall_start < fall_end, got {rs}, {rf}")
            w_rad = np.where(dist <= rs, 1.0, np.where(dist < rf, np.cos(0.5 * np.pi * (dist - rs) / (rf - rs)), 0.0))
            w = w_ang * w_rad
            bone = face.parts[m.attachment.part].bone if m.attachment.part in face.parts else "head"
            arr = dict(kind=MUSCLE_LINEAR, bone=BONE_NAMES.index(bone) if bone in BONE_NAMES else 0, point=a,
                       u=np.zeros(3), v=np.zeros(3), scale=1.0)
        elif m.kind == "sphincter":
            c = face.surface_point_position(m.attachment)
            axes = np.asarray(m.axes, dtype=np.float64).reshape(2, 3)
            semi = np.asarray(m.semi_axes, dtype=np.float64).reshape(2)
            d = points - c
            r = np.sqrt((d @ axes[0] / semi[0]) ** 2 + (d @ axes[1] / semi[1]) ** 2)
            # depth limit: only skin near the sphincter's plane (within the smaller semi-axis)
            normal = np.cross(axes[0], axes[1])
            depth = np.abs(d @ normal)
            w = np.where((r < 1.0) & (depth < semi.max()), np.cos(0.5 * np.pi * r), 0.0)
            arr = dict(kind=MUSCLE_SPHINCTER, bone=0, point=c, u=axes[0], v=axes[1], scale=float(semi.max()))
        else:
            raise ValueError(f"muscle {m.name!r}: unknown kind {m.kind!r} (expected 'linear' or 'sphincter')")
        out.append((arr, np.where(allowed, w, 0.0)))
    return out


def skin_model(face: FaceModel, device: str = "cpu", fields: list[PullField] | None = None,
               params: dict | None = None, only: np.ndarray | None = None,
               like: SkinModel | None = None, lid_contact: bool = True) -> SkinModel:
    """The SkinModel of `face` on `device` ("cpu" or "cuda"), with extra pull `fields`.

    params override `face.layer_params` and the module defaults (see module docstring).
    only: (V,) bool, the skin vertices that may move; the rest moves with its hold, as
    skin far from any muscle does (a part of the face simulated alone: a calibration's
    probe of FAPs that move only that part). like: the model of the same face, fields and
    params without `only`, whose jaw weights, stable substep and what depends on the face
    alone (edges, normals, muscle weights, seen skin) the part takes: the same steps, so the
    part settles as that skin does in the whole, and a part costs 30-40 ms to make.
    lid_contact: whether a closing upper lid stops on the lower lid's margin (lid_pairs).
    """
    p = dict(DEFAULTS)
    p.update({k: v for k, v in (face.layer_params or {}).items() if k in DEFAULTS})
    p.update(params or {})
    checked_params(p)
    fields = fields or []
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    F = np.asarray(face.skin_faces, dtype=np.int64)
    nv = len(V)
    thickness = np.asarray(face.skin_thickness, dtype=np.float64)
    if thickness.shape != (nv,):
        raise ValueError(f"skin_thickness: expected shape ({nv},), got {thickness.shape}")
    if not np.all(np.isfinite(thickness)) or np.any(thickness < 0):
        raise ValueError("skin_thickness: expected finite non-negative depths in metres")
    thickness = np.maximum(thickness, 1e-3)
    fr = np.asarray(p["layer_depth_fractions"], dtype=np.float64)

    if like is not None and like.skin_jaw.shape != (nv,):
        raise ValueError(f"like: a model of {len(like.skin_jaw)} skin vertices, this face has {nv}")
    # (what depends on the face alone a part shares with the whole: its edges, adjacency,
    # normals, muscle weights and seen skin)
    shared = like._face_setup if like is not None and like._face_setup is not None else None
    edges, A, normals, weights = shared[:4] if shared else (None, None, None, None)
    if shared is None:
        edges = mesh_edges(F)
        A = adjacency_from_edges(nv, edges)
        normals = vertex_normals(V, F)
        weights = _muscle_weights(face, V)
    layers = [V - normals * (thickness * fr[k])[:, None] for k in range(LAYER_COUNT)]

    # How much each skin vertex's hold follows the jaw (0: skull, 1: mandible).
    jaw = jaw_weights(face, layers[-1], A, p) if like is None else like.skin_jaw

    # Muscle and field weights on skin vertices; each vertex's drag (1/s), lowered by the
    # fields that ask for a quicker skin, by their weight (the strongest such field's)
    muscle_arrays, muscle_w, muscle_names, muscle_layers = [], [], [], []
    vertex_drag = np.full(nv, float(p["drag"]))
    for (arr, w), m in zip(weights, face.muscles):
        muscle_arrays.append(arr)
        muscle_w.append(w)
        muscle_names.append(m.name)
        muscle_layers.append((1,))
    for fld in fields:
        w = np.asarray(fld.skin_weight, dtype=np.float64)
        if w.shape != (nv,):
            raise ValueError(f"pull field {fld.name!r}: skin_weight must have shape ({nv},), got {w.shape}")
        d = np.asarray(fld.direction, dtype=np.float64)
        muscle_arrays.append(dict(kind=MUSCLE_FIELD, bone=0, point=np.zeros(3), u=d / np.linalg.norm(d),
                                  v=np.zeros(3), scale=1.0))
        muscle_w.append(w)
        muscle_names.append(fld.name)
        muscle_layers.append((0, 1))
        if fld.drag is not None:
            vertex_drag = np.minimum(vertex_drag, float(p["drag"]) + (float(fld.drag) - float(p["drag"]))
                                     * np.clip(w, 0.0, 1.0))

    # The simulated set: near any muscle or field, plus one ring that sits on its hold;
    # elsewhere the skin moves with its hold (`skin_positions`): the neck, the scalp and the
    # inside of the mouth, which no muscle of the model moves.
    touched = np.zeros(nv, dtype=bool)
    for w in muscle_w:
        touched |= w > 0
    active = dilate(touched, A, int(p["active_rings"]))
    if only is not None:
        only = np.asarray(only, dtype=bool)
        if only.shape != (nv,):
            raise ValueError(f"only: expected shape ({nv},), got {only.shape}")
        active &= only
        if not active.any():  # (a solver of nothing to move has nothing to launch)
            raise ValueError("only: none of these skin vertices is simulated (all move with their holds)")
    simulated = dilate(active, A, 1)
    sim_vertices = np.flatnonzero(simulated)
    nsv = len(sim_vertices)
    local = np.full(nv, -1, dtype=np.int64)
    local[sim_vertices] = np.arange(nsv)

    def pid(layer: int, verts: np.ndarray) -> np.ndarray:
        return layer * nsv + local[verts]

    P = LAYER_COUNT * nsv
    q = np.concatenate([layers[k][sim_vertices] for k in range(LAYER_COUNT)])
    area = vertex_areas(V, F)[sim_vertices]
    m_layer = np.maximum(area * thickness[sim_vertices] / LAYER_COUNT * float(p["density"]), 1e-9)
    mass = np.tile(m_layer, LAYER_COUNT)
    movable = np.tile(active[sim_vertices], LAYER_COUNT)
    inv_mass = np.where(movable, 1.0 / mass, 0.0)
    layer_of = np.repeat(np.arange(LAYER_COUNT), nsv)

    # Springs: only those touching a movable particle.
    se = edges[simulated[edges[:, 0]] & simulated[edges[:, 1]]]
    pairs, kappas = [], []
    for k, key in enumerate(("kappa_epidermis", "kappa_middle", "kappa_deep")):
        pairs.append(np.column_stack([pid(k, se[:, 0]), pid(k, se[:, 1])]))
        kappas.append(np.full(len(se), float(p[key])))
    for k in range(LAYER_COUNT - 1):
        pairs.append(np.column_stack([pid(k, sim_vertices), pid(k + 1, sim_vertices)]))
        kappas.append(np.full(nsv, float(p["kappa_vertical"])))
        pairs.append(np.column_stack([pid(k, se[:, 0]), pid(k + 1, se[:, 1])]))
        pairs.append(np.column_stack([pid(k, se[:, 1]), pid(k + 1, se[:, 0])]))
        kappas += [np.full(len(se), float(p["kappa_cross"]))] * 2
    spr = np.concatenate(pairs)
    kap = np.concatenate(kappas)
    keep = movable[spr[:, 0]] | movable[spr[:, 1]]
    spr, kap = spr[keep], kap[keep]
    q32 = q.astype(np.float32)
    rest_len = np.linalg.norm(q32[spr[:, 0]].astype(np.float64) - q32[spr[:, 1]], axis=1)
    # stiffness per unit of the lighter end's mass: a light particle (a sliver triangle's
    # vertex) next to a heavy one is not made stiffer than kappa, so the stable substep
    # depends on kappa and the valence only (see fae.sim.solver)
    ks = kap * np.minimum(mass[spr[:, 0]], mass[spr[:, 1]])

    # Anchors: every movable deepest-layer particle, stiffly; the upper layers weakly
    # (tethers: the tissue's hold on what lies beneath, which gives the skin a single rest
    # shape to return to after any pose; without them, skin folded by extreme poses stayed
    # folded). The fixed ring follows its hold exactly.
    particle_jaw = np.tile(jaw[sim_vertices], LAYER_COUNT)
    anchor_k = np.where(layer_of == LAYER_COUNT - 1, float(p["kappa_anchor"]), float(p["kappa_tether"])) * mass
    anchor_k[~movable] = 0.0

    # Muscle influences on the particles.
    inf_m, inf_p, inf_w = [], [], []
    accel = float(p["muscle_acceleration"])
    for mi, (w, lays) in enumerate(zip(muscle_w, muscle_layers)):
        vs = np.flatnonzero((w > 0) & active)
        for layer in lays:
            pp = pid(layer, vs)
            inf_m.append(np.full(len(vs), mi))
            inf_p.append(pp)
            inf_w.append(w[vs] * mass[pp] * accel)
    inf_m = np.concatenate(inf_m) if inf_m else np.zeros(0, dtype=np.int64)
    inf_p = np.concatenate(inf_p) if inf_p else np.zeros(0, dtype=np.int64)
    inf_w = np.concatenate(inf_w) if inf_w else np.zeros(0)
    order = np.argsort(inf_p, kind="stable")
    inf_m, inf_p, inf_w = inf_m[order], inf_p[order], inf_w[order]
    row_influence_start = np.concatenate([[0], np.cumsum(np.bincount(inf_p, minlength=P))])
    # layer order: each upper-layer particle over its own vertex in the next layer
    below = np.where(layer_of == 0, np.arange(P) + nsv, -1)
    below[~movable] = -1
    up = q[:-nsv] - q[nsv:]
    height = np.linalg.norm(up, axis=1)
    normal = np.zeros((P, 3))
    normal[:-nsv] = up / np.maximum(height, 1e-12)[:, None]
    min_height = np.zeros(P)
    min_height[:-nsv] = float(p["layer_min_height"]) * height

    # Fold guard (fae.sim.folds): the triangles of the two upper layers with a movable corner
    # (the middle layer too: folded, it drags the epidermis over with it).
    tri = F[simulated[F].all(axis=1) & active[F].any(axis=1)]
    guard = np.concatenate([guarded_triangles(q, pid(k, tri), particle_jaw) for k in range(LAYER_COUNT - 1)])
    # and the epidermis's rest shape among neighbours, against creases
    # and its edges' strain, where the skin is seen (not the mouth's lining)
    names = list(face.region_names)
    region = np.asarray(face.skin_region)
    seen = ~np.isin(region, [names.index(r) for r in HIDDEN_REGIONS if r in names])
    crease, crease_neighbours, crease_rest = crease_vertices(
        q, pid(0, sim_vertices), np.column_stack([pid(0, se[:, 0]), pid(0, se[:, 1])]), particle_jaw, movable,
        limited=seen[se].all(axis=1))
    crease = crease[:nsv]  # the epidermis's particles come first
    # and the lips' contact (both lips' epidermis where they face each other)
    lips = []
    for name in ("lip_upper", "lip_lower"):
        v = sim_vertices[region[sim_vertices] == names.index(name)] if name in names else np.zeros(0, dtype=np.int64)
        lips.append(pid(0, v))
    lip = lip_pairs(q, lips[0], lips[1], particle_jaw, LIP_PAIR_REACH, neighbours=LIP_PAIR_NEIGHBOURS,
                    clearance=LIP_CLEARANCE)
    from fae.adapt.transfer import visible_skin

    seen_skin = shared[4] if shared else visible_skin(face)
    # and each upper lid's lining, kept from sinking below its front's margin (the same
    # contact, the lining as the upper partner): a blink's closing pulled the lining 2-3.5 mm
    # below the front, and the margin creased where the two met; nor rising much above it
    # (the margin rolled out as a blink opened: see EYE_UPPER_FRONT_KEEP)
    for name in UPPER_LID_REGIONS:
        if name not in names:
            continue
        lid = region == names.index(name)
        hidden = lid & ~seen_skin
        rim = lid & seen_skin & (A @ hidden.astype(np.float64) > 0)
        lip = np.concatenate([lip, lip_pairs(q, pid(0, np.flatnonzero(hidden & simulated)),
                                             pid(0, np.flatnonzero(rim & simulated)), particle_jaw,
                                             float(p["lip_reach"]), most_slack=LID_MARGIN_SLACK)])
    # and each eye's lids: the upper lid's margin stays above the lower lid's (from the whole
    # margin, in a part too: only the pairs go whose particles the part lacks, local -1)
    for (upper_name, lower_name), eye_name in zip(LID_REGION_PAIRS if lid_contact else (), EYE_PARTS):
        upper_margin, lower_margin = (lid_margin_vertices(face, n, eye_name, normals) for n in (upper_name, lower_name))
        if len(upper_margin) < 2 or len(lower_margin) < 2:
            continue
        # the upper lid's skin within LID_CONTACT_BAND above its margin, front and lining,
        # away from the eye's corners (held there, the corner's lining came out through its
        # front)
        over = V[:, 1] - np.interp(V[:, 0], V[upper_margin, 0], V[upper_margin, 1])
        x0, x1 = V[lower_margin[0], 0], V[lower_margin[-1], 0]
        inward = (V[:, 0] > x0 + LID_CORNER_SHARE * (x1 - x0)) & (V[:, 0] < x1 - LID_CORNER_SHARE * (x1 - x0))
        near = np.flatnonzero((region == names.index(upper_name)) & (over < LID_CONTACT_BAND) & inward & simulated)
        lip = np.concatenate([lip, lid_pairs(local[near], V[near], local[lower_margin], V[lower_margin],
                                             particle_jaw)])
    # (a pair is kept where the particle it moves can move)
    lip = lip[((lip["upper_share"] > 0.0) & movable[lip["upper"]]) | ((lip["upper_share"] < 1.0) & movable[lip["lower"]])]

    # Bone distance grids and which particles must stay outside them.
    sdf_values, sdf_origin, sdf_spacing = [], np.zeros((BONE_COUNT, 3)), np.ones(BONE_COUNT)
    phi_rest = np.full((BONE_COUNT, P), np.inf)
    for b, (bv, bf) in enumerate(_bone_mesh(face, name) for name in BONE_NAMES):
        if len(bf) == 0:
            sdf_values.append(None)
            continue
        vals, origin, spacing = signed_distance_grid(bv, bf, cell=float(p["sdf_cell"]), device=device)
        sdf_values.append(wp.array(vals, dtype=float, device=device))
        sdf_origin[b], sdf_spacing[b] = origin, spacing
        phi_rest[b] = sample_grid(vals, origin, spacing, q)[0]
    collide = movable & (layer_of < LAYER_COUNT - 1) & (phi_rest.min(axis=0) > 0.0005)
    # a particle closer to its rest place (in a bone's frame) than this cannot be inside that
    # bone (a distance field changes by at most the distance moved; 1 mm spare for the grid)
    clearance = np.clip(phi_rest - 0.001, 0.0, 1.0).T
    outer, lining, front = np.zeros(P, dtype=bool), np.zeros(P, dtype=bool), np.zeros(P, dtype=bool)
    banded = np.isin(region, [names.index(r) for r in EYE_BAND_REGIONS if r in names])
    lids = np.isin(region, [names.index(r) for r in EYE_BAND_REGIONS if r in names and r.startswith("eyelid")])
    upper_lids = np.isin(region, [names.index(r) for r in UPPER_LID_REGIONS if r in names])
    # (a few cheek vertices under the lid are hidden from outward rays too: not lining)
    upper_lining = np.zeros(P, dtype=bool)
    for mark, which in ((outer, banded & seen_skin), (lining, lids & ~seen_skin), (front, upper_lids & seen_skin),
                        (upper_lining, upper_lids & ~seen_skin)):
        mark[pid(0, sim_vertices[which[sim_vertices]])] = True
    sphere, sphere_max = eye_spheres(face, q, movable & (layer_of < LAYER_COUNT - 1), outer, lining, front,
                                     upper_lining)

    # Stable substep: the springs' largest eigenvalue of M^-1 K over all configurations and
    # the weakest (implicit) anchor (see fae.sim.solver); a part's rows are a principal
    # submatrix of the whole's (its eigenvalues never above): the whole's step holds for it
    drag = np.tile(vertex_drag[sim_vertices], LAYER_COUNT)
    share = shared[5] if shared else carried_share(face, A, p)
    carried_drag = drag * np.tile(share[sim_vertices], LAYER_COUNT)
    if like is not None:
        dt_max = like.dt_max
    else:
        omega2 = max_stiffness_rate(P, spr, ks, mass, movable)
        anchor_rate = float(np.min(anchor_k[movable] / mass[movable])) if np.any(movable) else 0.0
        dt_max = stable_substep(omega2, anchor_rate, float(p["drag"]), float(p["cfl"]))
        quick = movable & (drag < float(p["drag"]))
        if np.any(quick):
            # the skin a field lets follow sooner (less drag) has its own, softer, bound: the
            # largest eigenvalue of its rows of the network (a principal submatrix, never above
            # the whole's); its modes reach the rest of the skin only through the drag there
            dt_max = min(dt_max, stable_substep(max_stiffness_rate(P, spr, ks, mass, quick),
                                                float(np.min(anchor_k[quick] / mass[quick])),
                                                float(np.min(drag[quick])), float(p["cfl"])))

    def arr(x, dtype):
        return wp.array(np.ascontiguousarray(x), dtype=dtype, device=device)

    skin_particle = np.where(active, local, -1)
    ma = muscle_arrays
    model = SkinModel(
        device=device,
        particle_count=P,
        particle_q=arr(q32, wp.vec3),
        particle_mass=arr(mass.astype(np.float32), float),
        particle_inv_mass=arr(inv_mass.astype(np.float32), float),
        particle_layer=arr(layer_of.astype(np.int32), int),
        particle_collider=arr(collide.astype(np.int32), int),
        particle_clearance=arr(clearance.astype(np.float32), wp.vec2),
        particle_sphere=arr(sphere.astype(np.float32), wp.vec4),
        particle_sphere_max=arr(sphere_max.astype(np.float32), float),
        particle_drag=arr(drag.astype(np.float32), float),
        particle_carried_drag=arr(carried_drag.astype(np.float32), float),
        spring_count=len(spr),
        spring_indices=arr(spr.reshape(-1).astype(np.int32), int),
        spring_rest_length=arr(rest_len.astype(np.float32), float),
        spring_stiffness=arr(ks.astype(np.float32), float),
        particle_jaw=arr(particle_jaw.astype(np.float32), float),
        particle_anchor_stiffness=arr(anchor_k.astype(np.float32), float),
        muscle_count=len(ma),
        muscle_names=muscle_names,
        muscle_kind=arr(np.array([m["kind"] for m in ma], dtype=np.int32), int),
        muscle_bone=arr(np.array([m["bone"] for m in ma], dtype=np.int32), int),
        muscle_point=arr(np.array([m["point"] for m in ma], dtype=np.float32).reshape(-1, 3), wp.vec3),
        muscle_axis_u=arr(np.array([m["u"] for m in ma], dtype=np.float32).reshape(-1, 3), wp.vec3),
        muscle_axis_v=arr(np.array([m["v"] for m in ma], dtype=np.float32).reshape(-1, 3), wp.vec3),
        muscle_scale=arr(np.array([m["scale"] for m in ma], dtype=np.float32), float),
        particle_below=arr(below.astype(np.int32), int),
        particle_normal=arr(normal.astype(np.float32), wp.vec3),
        particle_height=arr(min_height.astype(np.float32), float),
        row_influence_start=arr(row_influence_start.astype(np.int32), int),
        influence_count=len(inf_p),
        influence_muscle=arr(inf_m.astype(np.int32), int),
        influence_particle=arr(inf_p.astype(np.int32), int),
        influence_weight=arr(inf_w.astype(np.float32), float),
        contact_depth=float(p["contact_depth"]),
        triangle_count=len(guard),
        triangle_guard=wp.array(guard, dtype=GuardedTriangle, device=device),
        fold_min_area=float(p["fold_min_area"]),
        fold_passes=int(p["fold_passes"]),
        crease_vertex=wp.array(crease, dtype=CreaseVertex, device=device),
        crease_neighbours=arr(crease_neighbours, int),
        crease_rest_length=arr(crease_rest, float),
        crease_tolerance=float(p["crease_tolerance"]),
        strain_max=float(p["strain_max"]),
        strain_min=float(p["strain_min"]),
        lip_pair_count=len(lip),
        lip_pair=wp.array(lip, dtype=LipPair, device=device),
        sdf_values=sdf_values,
        sdf_origin=sdf_origin,
        sdf_spacing=sdf_spacing,
        skin_particle=skin_particle,
        skin_jaw=jaw,
        skin_rest=V.copy(),
        dt_max=dt_max,
        damping=float(p["drag"]),
        jaw_pivot=np.asarray(face.jaw_pivot, dtype=np.float64).copy(),
        jaw_axis=np.asarray(face.jaw_axis, dtype=np.float64).copy(),
    )
    model._face_setup = (edges, A, normals, weights, seen_skin, share)
    return model


def skin_positions(model: SkinModel, particle_q: np.ndarray, bone_rotation: np.ndarray | None = None,
                   bone_translation: np.ndarray | None = None) -> np.ndarray:
    """(V, 3) float64 metres: skin vertices from epidermis particle positions (P, 3) and the
    bone poses (BONE_COUNT, 3, 3), (BONE_COUNT, 3) (None: at rest). Skin that is not
    simulated is carried by its hold: (1 - w) x (skull pose of rest) + w x (jaw pose of rest),
    w its jaw weight (the numpy twin of fae.sim.skin)."""
    rest = model.skin_rest
    if bone_rotation is None:
        out = rest.copy()
    else:
        R, t = np.asarray(bone_rotation, dtype=np.float64), np.asarray(bone_translation, dtype=np.float64)
        w = model.skin_jaw[:, None]
        out = (rest @ R[0].T + t[0]) * (1.0 - w) + (rest @ R[1].T + t[1]) * w
    sim = model.skin_particle >= 0
    out[sim] = particle_q[model.skin_particle[sim]]
    return out
