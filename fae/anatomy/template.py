"""The shipped generic head: an anatomical FaceModel built from the fields of template_shapes.

    build_template() -> FaceModel      deterministic: the same arrays on every build

The built head ships as fae/data/generic_head.glb (fae.data.shipped_head_path).

Every surface is meshed from a signed distance field by marching cubes on the x >= 0 half
of a regular grid, decimated by quadric error and mirrored, so each mesh is exactly
symmetric and its midline vertices lie on x = 0. The skin is one closed surface: the mouth
slit separates the upper from the lower lip and opens into a pouch (the mouth cavity), and
the eyelids wrap a socket around each eyeball with an almond-shaped opening.
"""

from __future__ import annotations

import numpy as np

from fae import __version__
from fae.anatomy import template_shapes as S
from fae.anatomy.geometry import (
    collapse_caps,
    collapse_short_edges,
    decimate,
    largest_component,
    mesh_from_sdf,
    flip_caps,
    flip_to_delaunay,
    mirror_half,
    ray_hits,
    refine_long_triangles,
)
from fae.anatomy.surface_points import vertex_point
from fae.anatomy.template_muscles import template_muscles
from fae.anatomy.template_regions import REGION_NAMES, skin_regions
from fae.io.facemodel import FaceModel, Part, SurfacePoint
from fae.mpeg4 import FEATURE_POINTS

MM = 1e-3  # the shape fields are in millimetres

SKIN_STEP = 1.0  # mm, marching-cubes grid of the skin
SKIN_HALF_FACES = 9000  # about 9,000 skin vertices in all before the neck is refined
# The neck's straight sides decimate into slivers 45 mm long; fitted to a scan they move
# column by column and show as vertical ridges. Below NECK_REFINE_BELOW (mm, under the chin)
# no edge is longer than MAX_EDGE (mm).
NECK_REFINE_BELOW = -125.0
MAX_EDGE = 10.0
# Decimation also leaves caps (a corner of nearly 180 degrees: three corners almost in a
# line, 0.2 mm high across 9 mm) where the skin is flat enough to flip their long edge:
# such a triangle turns over at the slightest motion, so a fit lets the scan go around it
# (a patch of the inner eye corner off a scan by 5-8 mm) and the skin check counts it as
# a crease. Edges between faces within FLIP_DIHEDRAL degrees of flat are flipped to
# Delaunay (the shape is unchanged: no vertex moves).
FLIP_DIHEDRAL = 35.0
FLIP_KEPT_REGIONS = ("lip_upper", "lip_lower", "mouth_cavity", "eyelid_upper_l", "eyelid_upper_r",
                     "eyelid_lower_l", "eyelid_lower_r")
# The upper lids keep their edges (above) but not their caps: a cap (a corner over
# CAP_ANGLE, its apex 0.2-0.4 mm off the long edge) turns over as the lid closes and showed
# as a crease on every blink. Their long edge is flipped where that changes the lid's shape
# by at most CAP_FLIP_CHANGE (fae.anatomy.geometry.flip_caps). From 120 degrees, the
# flipped lid's short edges compressed to 0.25 of their length as it closed.
# Not here in the lips (the upper lip's are flipped on the finished skin:
# LIP_CAP_FLIPPED_REGIONS, below); flipped here in the lower lip, its inner band shaded
# jagged when the mouth opened; not in the lower lids: the brows' calibration then drove a frightened face's
# forehead into folds.
CAP_FLIPPED_REGIONS = ("eyelid_upper_l", "eyelid_upper_r")
# The upper lip's caps go too (8 of its visible faces had a corner over 150 degrees, the
# highest 169): a cap's normal turned over as soon as the lip moved, and the skin check
# counted it and its neighbour as a fold (disgust's upper lip, the expressions' and
# visemes' most frequent folds). They are flipped on the finished skin, where no vertex
# moves any more (tried flipped with the lids' in symmetric_mesh, before reshaped_skin, the
# shaping moved the upper lip and nose by up to 2.4 mm, and the feature points with them).
# The flip runs on the whole mirrored skin: its vertices are exactly symmetric, so each cap
# and its mirror image flip alike (test_skin_is_mirror_symmetric checks the faces).
LIP_CAP_FLIPPED_REGIONS = ("lip_upper",)
CAP_ANGLE = 130.0  # degrees
CAP_FLIP_CHANGE = 0.5  # mm
# The lower lip's inner rim is a sharp edge, and the decimation left caps lying along it
# (three rim vertices in one face, a corner of 150-170 degrees, 0.2 mm high across 3.5 mm):
# a cap's normal is the mean of the rim's two sides and turns over as soon as the rim bends,
# and the skin check counted it and its neighbours as a crease in every stream (most of the
# lower lip's folds). Flipped (flip_caps), the rim turned jagged as the mouth opened; each
# cap's apex is merged into the nearer end of its long edge instead
# (fae.anatomy.geometry.collapse_caps), the rim keeping its run of edges. Not in the upper
# lip: merged there, its edge rose unevenly as lower_t_midlip and its twins raised it (1.2
# against 3.8 mm, a row of teeth) and a head made from a photo folded a triangle.
# The lower lids' outer corners carry caps too (a corner of 174 degrees, 0.08 mm high
# across 3.6 mm, at the canthus): as a blink lowered the upper lid the cap turned over and
# creased the faces beside it (3 a side in every blinking stream). There the nearer end
# would turn the face beside the cap over, and the apex goes to the farther one
# (CAP_FAR_END_REGIONS); in the lower lip the farther end was tried and not kept: the two
# mouth-corner caps it merged left edges that stretched 2.8x as viseme 14 narrowed the mouth.
CAP_COLLAPSED_REGIONS = ("lip_lower", "eyelid_lower_l", "eyelid_lower_r")
CAP_FAR_END_REGIONS = ("eyelid_lower_l", "eyelid_lower_r")
CAP_COLLAPSE_ANGLE = 150.0  # degrees
# The lips' rims near the mouth corners kept edges of 0.5-0.6 mm among 3-5 mm ones, with
# needles beside them (corners of 6-10 degrees): a needle's normal turned over as soon as
# the corner moved, and creased the lip's top against it in most frames of every stream
# (the lower lip's 8-14 folded triangles a stream, the upper lip's few). Edges shorter than
# SHORT_EDGE are merged away in SHORT_EDGE_REGIONS (fae.anatomy.geometry.collapse_short_edges).
SHORT_EDGE_REGIONS = ("lip_upper", "lip_lower")
SHORT_EDGE = 0.7  # mm
NEEDLE_GAP = 0.05  # mm
THICKNESS_CAP = 0.025  # m, soft-tissue depth reported where no bone lies below
LAYER_DEPTH_FRACTIONS = [0.0, 0.35, 1.0]
# the gnathion's direction from the face (y up, z forward): 30 degrees forward of straight down
GNATHION_DIRECTION = np.array([0.0, -np.cos(np.radians(30.0)), np.sin(np.radians(30.0))])
SKIN_COLOR = np.array([0.745, 0.42, 0.31, 1.0], dtype=np.float32)  # linear RGB of a light skin tone

# The mandible's ramus decimates into faces 2-3 cm long. Pushed in under a thin jaw's skin
# (fae.adapt.transfer.push_under_skin), two of them folded along their long edge and the
# fold was blended back over everything within two rings of it, up to the jaw's angle 25 mm
# away, leaving the skin there inside the bone (a bust refused as not whole). The faces
# with an edge over LONG_EDGE mm (the ramus's, none elsewhere) and their neighbours are
# refined: their edges between two of them are split to MAX_EDGE, so that no edge over
# LONG_EDGE is left (the ring's outer edges keep up to 19 mm); the rest keep the
# decimation's triangles (the chin's muscles are attached where they are).
REFINED_PARTS = ("mandible",)
LONG_EDGE = 20.0
# (field, grid box lo/hi in mm for the x >= 0 half, grid step mm, faces in the half mesh)
_PART_SPECS = {
    "cranium": (S.cranium_sdf, (0.0, -110.0, -115.0), (85.0, 125.0, 115.0), 2.0, 4000),
    "mandible": (S.mandible_sdf, (0.0, -130.0, -10.0), (65.0, -5.0, 100.0), 1.25, 1500),
    "upper_teeth": (S.upper_teeth_sdf, (0.0, -84.0, 20.0), (40.0, -60.0, 95.0), 0.6, 1200),
    "lower_teeth": (S.lower_teeth_sdf, (0.0, -100.0, 20.0), (40.0, -76.0, 95.0), 0.6, 1200),
    "tongue": (S.tongue_sdf, (0.0, -96.0, 14.0), (25.0, -74.0, 82.0), 1.0, 500),
}
_PART_COLORS = {
    "cranium": (0.80, 0.75, 0.62, 1.0),
    "mandible": (0.80, 0.75, 0.62, 1.0),
    "upper_teeth": (0.88, 0.86, 0.78, 1.0),
    "lower_teeth": (0.88, 0.86, 0.78, 1.0),
    "tongue": (0.62, 0.18, 0.18, 1.0),
    "eye_l": (0.92, 0.92, 0.90, 1.0),
    "eye_r": (0.92, 0.92, 0.90, 1.0),
}
_BONES = {"cranium": "head", "upper_teeth": "head", "mandible": "jaw", "lower_teeth": "jaw", "tongue": "tongue",
          "eye_l": "eye_l", "eye_r": "eye_r"}
IRIS_COLOR = np.array([0.10, 0.22, 0.30, 1.0], dtype=np.float32)
PUPIL_COLOR = np.array([0.005, 0.005, 0.005, 1.0], dtype=np.float32)


def _unflipped(V: np.ndarray) -> np.ndarray:
    """(n,) bool: skin vertices (mm) that keep the decimation's edges: those of the lips,
    the mouth's lining and the eyelids, whose margins meet and part (flipped there, the
    mouth corners tore open on a wide viseme), and those within NEEDLE_GAP of another
    vertex (a cluster of needles beside the nose: flipped, it cut through itself in a fit)."""
    from scipy.spatial import cKDTree

    region = skin_regions(V, None)
    kept = np.isin(region, [REGION_NAMES.index(r) for r in FLIP_KEPT_REGIONS])
    kept[cKDTree(V).query_pairs(NEEDLE_GAP, output_type="ndarray").ravel()] = True
    return kept


def _in_regions(regions: tuple[str, ...]):
    """A function of skin vertices V (n, 3) mm giving (n,) bool: those in `regions` (the
    faces whose caps are flipped or merged, or whose short edges are merged)."""
    return lambda V: np.isin(skin_regions(V, None), [REGION_NAMES.index(r) for r in regions])


# --- meshes ----------------------------------------------------------------------------------

NAPE_REGIONS = ("neck", "jaw_l", "jaw_r")


def _onto_along_rays(P: np.ndarray, field, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(k, 3): each point P (k, 3) moved along its ray origin + t direction ((k, 3) each,
    direction unit, P on the ray) to the nearest crossing of field's zero set beyond it or
    before it (whichever side P lies on), mm: 1 mm steps, then bisection."""
    t0 = np.einsum("ij,ij->i", P - origin, direction)

    def at(t):
        return origin + t[:, None] * direction

    sign = np.where(field(at(t0)) < 0.0, 1.0, -1.0)  # inside: go on outwards, else back in
    lo, hi = t0.copy(), t0.copy()
    going = np.ones(len(P), dtype=bool)
    for _ in range(80):
        lo[going] = hi[going]
        hi[going] += sign[going]
        going &= (field(at(hi)) < 0.0) == (sign > 0)
        if not going.any():
            break
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        inside = field(at(mid)) < 0.0
        lo = np.where(inside == (sign > 0), mid, lo)
        hi = np.where(inside == (sign > 0), hi, mid)
    return at(0.5 * (lo + hi))


def _nape_rays(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays out from the neck's axis at each point's height (the back of the neck is
    star-shaped about it: the notch's walls keep their order)."""
    d = P[:, [0, 2]] - S.NECK_AXIS_XZ
    u = d / np.linalg.norm(d, axis=1)[:, None]
    origin = np.column_stack([np.full(len(P), S.NECK_AXIS_XZ[0]), P[:, 1], np.full(len(P), S.NECK_AXIS_XZ[1])])
    return origin, np.column_stack([u[:, 0], np.zeros(len(P)), u[:, 1]])


def _front_rays(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays straight forward (+z) through each point (the philtrum faces the front)."""
    origin = P.copy()
    origin[:, 2] = 0.0
    return origin, np.tile([0.0, 0.0, 1.0], (len(P), 1))


def reshaped_skin(V: np.ndarray, F: np.ndarray, region: np.ndarray, relax: int = 8) -> np.ndarray:
    """(n, 3) mm: the skin vertices V (n, 3) mm that the reshaped skin
    (template_shapes.skin_sdf with reshaped) moves, moved onto it: the neck's and jaw's
    each along its ray from the neck's axis, the face's (the philtrum) straight forward or
    back, then `relax` rounds of tangential smoothing back onto it, each along its rays
    (a notch's walls land packed into thin bands, which fold at the first squeeze; the
    philtrum's vertices, left where their rays put them, bunch under the nose and shade
    it jagged: smoothed, they slide up to 4.7 mm over the groove and the upper lip, its
    triangles' areas changing 0.3-7x)."""
    from fae.mesh import adjacency, vertex_normals

    V = np.asarray(V, dtype=np.float64)

    def shaped(P):
        return S.skin_sdf(P, reshaped=True)

    changed = np.abs(shaped(V) - S.skin_sdf(V)) > 1e-3
    nape = changed & np.isin(region, [REGION_NAMES.index(r) for r in NAPE_REGIONS])
    front = changed & ~nape & (V[:, 2] > 0.0)
    A = adjacency(np.asarray(F, dtype=np.int64), len(V))
    degree = np.asarray(A.sum(axis=1)).ravel()
    W = V.copy()
    moves = [(m, rays) for m, rays in ((nape, _nape_rays), (front, _front_rays)) if m.any()]
    for m, rays in moves:
        W[m] = _onto_along_rays(V[m], shaped, *rays(V[m]))
    for _ in range(relax):
        N = vertex_normals(W, F)
        for m, rays in moves:
            step = (A @ W)[m] / degree[m, None] - W[m]
            step -= np.sum(step * N[m], axis=1, keepdims=True) * N[m]
            P = W[m] + step
            W[m] = _onto_along_rays(P, shaped, *rays(P))
    return W


def _below_the_chin(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m,) bool: faces of mesh V (n, 3) mm, F (m, 3) whose centre lies below NECK_REFINE_BELOW."""
    return V[F].mean(axis=1)[:, 1] < NECK_REFINE_BELOW


def _with_long_edges(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m,) bool: faces of mesh V (n, 3) mm, F (m, 3) with an edge longer than LONG_EDGE, and
    the faces that share a corner with them (room for the split edges' neighbours)."""
    long = np.linalg.norm(V[F] - V[F][:, [1, 2, 0]], axis=2).max(axis=1) > LONG_EDGE
    near = np.zeros(len(V), dtype=bool)
    near[F[long].ravel()] = True
    return near[F].any(axis=1)


def symmetric_mesh(sdf, lo, hi, step: float, half_faces: int, refined=None,
                   kept_edges=None, cap_flipped=None, cap_collapsed=None,
                   cap_far_end=None, short_edges_merged=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mirror-symmetric closed mesh of `sdf < 0` (mm): (V (n, 3) mm, F (m, 3), mirror (n,)).

    refined: None, or a function of the decimated half mesh (V (n, 3) mm, F (m, 3)) giving
    (m,) bool: an edge between two of those faces is split until none is longer than
    MAX_EDGE (the decimation leaves centimetre-long slivers where the surface is straight);
    kept_edges: None, or a function of the vertices V (n, 3) mm giving (n,) bool: the edges
    between faces within FLIP_DIHEDRAL of flat are flipped to Delaunay (caps removed),
    except in faces with a corner it marks; cap_flipped: None, or such a function marking
    vertices whose faces (two corners marked or more: the lid's crease runs along its
    border with the forehead) lose their caps (flip_caps) after that; cap_collapsed: None, or
    such a function marking vertices whose faces (two corners marked or more) have their caps
    over CAP_COLLAPSE_ANGLE merged away (collapse_caps) last, into the farther end of their
    long edge where the nearer one fails in faces cap_far_end (such a function) marks;
    short_edges_merged: None, or such a function marking vertices whose faces' edges
    shorter than SHORT_EDGE are merged away (collapse_short_edges) after that."""
    V, F = mesh_from_sdf(sdf, lo, hi, step, pad=False)
    V, F = largest_component(V, F)
    V, F = decimate(V, F, half_faces)
    if refined is not None:
        V, F = refine_long_triangles(V, F, MAX_EDGE, refined(V, F))
    if kept_edges is not None:
        F = flip_to_delaunay(V, F, ~kept_edges(V)[F].any(axis=1), max_dihedral=FLIP_DIHEDRAL)
    if cap_flipped is not None:
        F = flip_caps(V, F, cap_flipped(V)[F].sum(axis=1) >= 2, cap_angle=CAP_ANGLE, max_change=CAP_FLIP_CHANGE)
    if cap_collapsed is not None:
        far = None if cap_far_end is None else cap_far_end(V)[F].sum(axis=1) >= 2
        V, F = collapse_caps(V, F, cap_collapsed(V)[F].sum(axis=1) >= 2, cap_angle=CAP_COLLAPSE_ANGLE, far_end=far)
    if short_edges_merged is not None:
        V, F = collapse_short_edges(V, F, short_edges_merged(V)[F].sum(axis=1) >= 2, SHORT_EDGE)
    return mirror_half(V, F, tol=1e-9)


def eyeball(center_mm: np.ndarray, rings: int = 40, segments: int = 48) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eyeball looking along +Z: (V (n, 3) m, F (m, 3), vertex colours (n, 4)); vertex 0 is the pupil centre."""
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]  # polar angle from +Z
    phi = 2.0 * np.pi * np.arange(segments) / segments
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([np.broadcast_to(st * np.cos(phi), (len(theta), segments)),
                     np.broadcast_to(st * np.sin(phi), (len(theta), segments)),
                     np.broadcast_to(ct, (len(theta), segments))], axis=-1).reshape(-1, 3)
    unit = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    n_ring = len(theta)
    faces = []
    top, bottom = 0, len(unit) - 1
    idx = lambda r, s: 1 + r * segments + (s % segments)  # noqa: E731
    for s in range(segments):
        faces.append((top, idx(0, s), idx(0, s + 1)))
        faces.append((bottom, idx(n_ring - 1, s + 1), idx(n_ring - 1, s)))
    for r in range(n_ring - 1):
        for s in range(segments):
            a, b, c, d = idx(r, s), idx(r, s + 1), idx(r + 1, s), idx(r + 1, s + 1)
            faces.append((a, c, b))
            faces.append((b, c, d))
    F = np.array(faces, dtype=np.int64)
    angle = np.arccos(np.clip(unit[:, 2], -1.0, 1.0))
    colors = np.tile(np.array(_PART_COLORS["eye_l"], dtype=np.float32), (len(unit), 1))
    colors[angle < np.arcsin(S.IRIS_RADIUS / S.EYE_RADIUS)] = IRIS_COLOR
    colors[angle < np.arcsin(S.PUPIL_RADIUS / S.EYE_RADIUS)] = PUPIL_COLOR
    V = (center_mm + S.EYE_RADIUS * unit) * MM
    return V, F, colors


# teeth toward the back of the arch darken to TEETH_BACK_SHADE of their colour between these
# angles about the arch's centre (0: the front midline, 90: straight to the side): the
# cheeks shade the premolars and molars (the buccal corridor); lit like the incisors, the
# lower arch's sides stood at the corners of an open smile as two white fangs
TEETH_SHADE_FROM, TEETH_SHADE_TO = 30.0, 60.0
TEETH_BACK_SHADE = 0.12


def teeth_colors(name: str, V: np.ndarray) -> np.ndarray:
    """(n, 4) float32 linear RGBA of the teeth part `name` at its vertices V (n, 3) mm: its
    colour, darker towards the back of the arch (TEETH_SHADE_FROM..TEETH_SHADE_TO)."""
    a, b = S.UPPER_ARCH if name == "upper_teeth" else S.LOWER_ARCH
    angle = np.degrees(np.arctan2(np.abs(V[:, 0]) / a, (V[:, 2] - S.ARCH_CENTER_Z) / b))
    t = np.clip((angle - TEETH_SHADE_FROM) / (TEETH_SHADE_TO - TEETH_SHADE_FROM), 0.0, 1.0)
    shade = 1.0 - (1.0 - TEETH_BACK_SHADE) * t * t * (3.0 - 2.0 * t)
    colors = np.tile(np.array(_PART_COLORS[name], dtype=np.float32), (len(V), 1))
    colors[:, :3] *= shade[:, None].astype(np.float32)
    return colors


def _part(name: str, V: np.ndarray, F: np.ndarray, vertex_colors=None) -> Part:
    return Part(vertices=np.ascontiguousarray(V, dtype=np.float64), faces=np.ascontiguousarray(F, dtype=np.int32),
                color=np.array(_PART_COLORS[name], dtype=np.float32), bone=_BONES[name], vertex_colors=vertex_colors)


# --- surface points --------------------------------------------------------------------------

def _nearest(V: np.ndarray, candidates: np.ndarray, target) -> int:
    """Index (into V) of the candidate vertex nearest to target; ties go to the lower index."""
    d = np.linalg.norm(V[candidates] - np.asarray(target, dtype=np.float64), axis=1)
    return int(candidates[np.argmin(d)])


def _front(V: np.ndarray, F: np.ndarray, x: float, y: float) -> np.ndarray:
    """(3,) the outermost skin point straight in front of (x, y) (mm)."""
    hit = ray_hits(V, F, np.array([[x, y, 160.0]]), np.array([[0.0, 0.0, -1.0]]))[0]
    if not np.all(np.isfinite(hit)):
        raise RuntimeError(f"template: no skin in front of x={x} y={y} mm")
    return hit


def skin_feature_vertices(V: np.ndarray, F: np.ndarray, mirror: np.ndarray, region: np.ndarray) -> dict[str, int]:
    """FDP name -> skin vertex for every FDP on the skin (mm mesh, left points chosen, right mirrored)."""
    names = {n: i for i, n in enumerate(REGION_NAMES)}
    in_region = lambda *rs: np.flatnonzero(np.isin(region, [names[r] for r in rs]))  # noqa: E731
    mid = np.flatnonzero(V[:, 0] == 0.0)
    mid_in = lambda *rs: np.intersect1d(mid, in_region(*rs))  # noqa: E731
    left = np.flatnonzero(V[:, 0] > 0.0)
    left_in = lambda *rs: np.intersect1d(left, in_region(*rs))  # noqa: E731
    e = S.EYE_CENTER
    y0, g = S.STOMION_Y, 0.5 * S.LIP_GAP
    out: dict[str, int] = {}

    # chin and jaw
    chin_mid = mid_in("chin")
    # the bottom of the chin as the face shows it: the most anterior-inferior midline point
    # (30 degrees forward of straight down, the gnathion), not the lowest one, which on a
    # nearly level underside lies anywhere back to the neck (25 mm behind, where the jaw's
    # turn moves it mostly backwards and open_jaw then turned the jaw 1.5x as far)
    out["2.1"] = int(chin_mid[np.argmax(V[chin_mid] @ GNATHION_DIRECTION)])
    out["2.10"] = _nearest(V, chin_mid, _front(V, F, 0.0, -104.0))
    out["2.11"] = _nearest(V, left_in("chin", "jaw_l"), _front(V, F, 17.0, -108.0))
    out["2.13"] = _nearest(V, left_in("jaw_l", "neck"), (62.0, -100.0, 4.0))
    # lips: inner contour is the front edge of the slit, outer contour the vermilion border
    upper_mid = mid_in("lip_upper")
    edge = upper_mid[V[upper_mid, 1] < y0 + g + 0.8]
    out["2.2"] = int(edge[np.argmax(V[edge, 2])])
    lower_mid = mid_in("lip_lower")
    edge = lower_mid[V[lower_mid, 1] > y0 - g - 0.8]
    out["2.3"] = int(edge[np.argmax(V[edge, 2])])
    corner = S.MOUTH_HALF_WIDTH
    out["8.3"] = _nearest(V, left_in("lip_upper", "lip_lower"), (corner + 1.0, y0, 86.0))
    out["2.4"] = _nearest(V, left_in("lip_upper", "lip_lower"), (corner - 2.5, y0, 86.0))
    for name, x, sign, reg in (("2.6", 0.5 * corner, 1, "lip_upper"), ("2.8", 0.5 * corner, -1, "lip_lower")):
        cand = left_in(reg)
        cand = cand[np.abs(V[cand, 1] - (y0 + sign * g)) < 1.0]
        target = np.array([x, y0 + sign * g, 110.0])
        out[name] = _nearest(V, cand, target)
    out["8.1"] = _nearest(V, mid_in("lip_upper"), _front(V, F, 0.0, y0 + 8.2))
    out["8.2"] = _nearest(V, mid_in("lip_lower"), _front(V, F, 0.0, y0 - 9.4))
    out["8.5"] = _nearest(V, left_in("lip_upper"), _front(V, F, 13.0, y0 + 7.0))
    out["8.7"] = _nearest(V, left_in("lip_lower"), _front(V, F, 13.0, y0 - 8.5))
    out["8.10"] = _nearest(V, left_in("lip_upper"), _front(V, F, 5.0, y0 + 8.8))
    # eyes: lid margins over the pupil, corners, outer lid contours
    lid_up = left_in("eyelid_upper_l")
    lid_lo = left_in("eyelid_lower_l")
    r = S.EYE_RADIUS + S.EYE_GAP
    s = S.IRIS_RADIUS / r
    out["3.1"] = _nearest(V, lid_up, e + r * np.array([0.0, s, np.sqrt(1 - s * s)]))
    out["3.3"] = _nearest(V, lid_lo, e + r * np.array([0.0, -s, np.sqrt(1 - s * s)]))
    lids = np.union1d(lid_up, lid_lo)
    out["3.7"] = _nearest(V, lids, e + np.array([S.FISSURE_HALF_WIDTH, 0.4, 4.0]))
    out["3.11"] = _nearest(V, lids, e + np.array([-S.FISSURE_HALF_WIDTH, -0.4, 4.0]))
    out["3.13"] = _nearest(V, lid_up, _front(V, F, e[0], e[1] + 10.0))
    out["3.9"] = _nearest(V, lid_lo, _front(V, F, e[0], e[1] - 9.0))
    # eyebrows (left brow: 4.1 inner end, 4.3 top, 4.5 outer end)
    brow = left_in("forehead")
    out["4.1"] = _nearest(V, brow, _front(V, F, 15.0, 17.0))
    out["4.3"] = _nearest(V, brow, _front(V, F, 31.0, 21.0))
    out["4.5"] = _nearest(V, brow, _front(V, F, 46.0, 16.0))
    # cheeks
    out["5.1"] = _nearest(V, left_in("cheek_l"), _front(V, F, 40.0, -48.0))
    out["5.3"] = _nearest(V, left_in("cheek_l"), _front(V, F, 46.0, -16.0))
    # nose
    nose_mid = mid_in("nose")
    out["9.3"] = int(nose_mid[np.argmax(V[nose_mid, 2])])
    out["9.12"] = _nearest(V, nose_mid, _front(V, F, 0.0, -22.0))
    # the nose's bottom middle: on the columella's underside, 2.8 mm above where it meets
    # the philtrum's groove, where the old keel's 9.15 was: the mouth-nose separation (MNS,
    # the unit of every lip FAP) stays 22.8 mm (22.3 before); taken at the junction it was
    # 20.0 mm, and every mouth opened 10 % less
    out["9.15"] = _nearest(V, mid, (0.0, -54.5, 104.5))
    nose_left = left_in("nose")
    out["9.1"] = _nearest(V, nose_left, (20.0, -47.0, 98.0))
    out["9.5"] = _nearest(V, nose_left, (14.0, -53.0, 97.0))
    out["9.7"] = _nearest(V, nose_left, _front(V, F, 7.0, 2.0))
    out["9.13"] = _nearest(V, nose_left, _front(V, F, 8.0, -22.0))
    # ears
    ear = left_in("ear_l")
    out["10.1"] = int(ear[np.argmax(V[ear, 1])])
    out["10.5"] = int(ear[np.argmin(V[ear, 1])])
    out["10.3"] = int(ear[np.argmin(V[ear, 2])])
    contact = _region_border(F, region, names["ear_l"])
    contact = np.intersect1d(contact, left)
    out["10.9"] = int(contact[np.argmax(V[contact, 1])])
    out["10.7"] = int(contact[np.argmin(V[contact, 1])])
    # hairline and skull
    out["11.1"] = _nearest(V, mid, _front(V, F, 0.0, 72.0))
    out["11.3"] = _nearest(V, left, _front(V, F, 42.0, 62.0))
    top = mid[V[mid, 2] > -40.0]
    out["11.4"] = int(top[np.argmax(V[top, 1])])
    out["11.5"] = out["11.4"]  # a bald head: no hair over the top of the skull
    back = mid[V[mid, 1] > 0.0]
    out["11.6"] = int(back[np.argmin(V[back, 2])])

    by_name = {p.name: p for p in FEATURE_POINTS}
    for name in list(out):
        partner = by_name[name].mirror
        if partner != name:
            out[partner] = int(mirror[out[name]])
    return out


def _region_border(F: np.ndarray, region: np.ndarray, r: int) -> np.ndarray:
    """Vertices of region r that share a face with another region."""
    fr = region[F]
    mixed = (fr == r).any(axis=1) & (fr != r).any(axis=1)
    verts = np.unique(F[mixed])
    return verts[region[verts] == r]


def part_feature_points(parts_mm: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, SurfacePoint]:
    """FDPs on rigid parts: pupils (3.5/3.6), teeth (9.8-9.11), tongue (6.x), top of the spine (7.1)."""
    out: dict[str, SurfacePoint] = {}
    out["3.5"] = vertex_point("eye_l", parts_mm["eye_l"][1], 0)
    out["3.6"] = vertex_point("eye_r", parts_mm["eye_r"][1], 0)

    def midline_extreme(part: str, key) -> SurfacePoint:
        V, F = parts_mm[part]
        mid = np.flatnonzero(V[:, 0] == 0.0)
        return vertex_point(part, F, int(mid[np.argmax(key(V[mid]))]))

    front_low = lambda W: W[:, 2] - 3.0 * W[:, 1]  # noqa: E731  incisal edge: forward and down
    front_high = lambda W: W[:, 2] + 3.0 * W[:, 1]  # noqa: E731
    out["9.10"] = midline_extreme("upper_teeth", front_low)   # bottom of the upper teeth
    out["9.8"] = midline_extreme("upper_teeth", front_high)   # top of the upper teeth
    out["9.11"] = midline_extreme("lower_teeth", front_high)  # top of the lower teeth
    out["9.9"] = midline_extreme("lower_teeth", front_low)    # bottom of the lower teeth
    out["6.1"] = midline_extreme("tongue", lambda W: W[:, 2])
    V, F = parts_mm["tongue"]
    mid = np.flatnonzero(V[:, 0] == 0.0)
    zc = 0.5 * (V[:, 2].min() + V[:, 2].max())
    out["6.2"] = vertex_point("tongue", F, _nearest(V, mid, (0.0, V[:, 1].max() + 1.0, zc)))
    left = int(np.lexsort((np.abs(V[:, 2] - zc), -V[:, 0]))[0])
    out["6.3"] = vertex_point("tongue", F, left)
    partner = _nearest(V, np.arange(len(V)), V[left] * np.array([-1.0, 1.0, 1.0]))
    out["6.4"] = vertex_point("tongue", F, partner)
    # 7.1: where the spine meets the skull, on the cranium's base above the neck
    V, F = parts_mm["cranium"]
    mid = np.flatnonzero(V[:, 0] == 0.0)
    base = mid[(V[mid, 2] > -30.0) & (V[mid, 2] < -5.0)]
    out["7.1"] = vertex_point("cranium", F, int(base[np.argmin(V[base, 1])]))
    return out


# --- skin attributes -------------------------------------------------------------------------

def skin_uv(V: np.ndarray) -> np.ndarray:
    """(n, 2) float32 cylindrical texture coordinates: u around the head (face at 0.5), v up."""
    u = 0.5 + np.arctan2(V[:, 0], V[:, 2]) / (2.0 * np.pi)
    lo, hi = V[:, 1].min(), V[:, 1].max()
    v = (V[:, 1] - lo) / (hi - lo)
    return np.clip(np.stack([u, v], axis=1), 0.0, 1.0).astype(np.float32)


def skin_thickness(V: np.ndarray, bones: list[tuple[np.ndarray, np.ndarray]], cap: float) -> np.ndarray:
    """(n,) distance from each skin vertex to the nearest bone surface, at most `cap` (V's unit)."""
    import trimesh

    depth = np.full(len(V), np.inf)
    for BV, BF in bones:
        mesh = trimesh.Trimesh(BV, BF, process=False)
        _, d, _ = trimesh.proximity.closest_point(mesh, V)
        depth = np.minimum(depth, d)
    return np.minimum(depth, cap)


# --- the whole head --------------------------------------------------------------------------

def build_template() -> FaceModel:
    """Build the generic head (about 15 s on one core). Deterministic."""
    V, F, mirror = symmetric_mesh(S.skin_sdf, (0.0, -240.0, -125.0), (100.0, 130.0, 130.0), SKIN_STEP, SKIN_HALF_FACES,
                                  refined=_below_the_chin, kept_edges=_unflipped,
                                  cap_flipped=_in_regions(CAP_FLIPPED_REGIONS),
                                  cap_collapsed=_in_regions(CAP_COLLAPSED_REGIONS),
                                  cap_far_end=_in_regions(CAP_FAR_END_REGIONS),
                                  short_edges_merged=_in_regions(SHORT_EDGE_REGIONS))
    region = skin_regions(V, F)
    V = reshaped_skin(V, F, region)
    V = 0.5 * (V + V[mirror] * np.array([-1.0, 1.0, 1.0]))  # exactly symmetric again
    lip_caps = np.isin(region, [REGION_NAMES.index(r) for r in LIP_CAP_FLIPPED_REGIONS])
    F = flip_caps(V, F, lip_caps[F].sum(axis=1) >= 2, cap_angle=CAP_ANGLE, max_change=CAP_FLIP_CHANGE)
    parts_mm: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, (sdf, lo, hi, step, half_faces) in _PART_SPECS.items():
        PV, PF, _ = symmetric_mesh(sdf, lo, hi, step, half_faces,
                                   refined=_with_long_edges if name in REFINED_PARTS else None)
        parts_mm[name] = (PV, PF)
    eye_r_center = S.EYE_CENTER * np.array([-1.0, 1.0, 1.0])
    eye_l = eyeball(S.EYE_CENTER)
    eye_r = eyeball(eye_r_center)
    parts_mm["eye_l"] = (eye_l[0] / MM, eye_l[1])
    parts_mm["eye_r"] = (eye_r[0] / MM, eye_r[1])

    feature_points: dict[str, SurfacePoint] = {}
    for name, vertex in skin_feature_vertices(V, F, mirror, region).items():
        feature_points[name] = vertex_point("skin", F, vertex)
    feature_points.update(part_feature_points(parts_mm))
    order = [p.name for p in FEATURE_POINTS]
    feature_points = {name: feature_points[name] for name in order}

    muscles = template_muscles(V, F, region, parts_mm)
    thickness = skin_thickness(V, [parts_mm["cranium"], parts_mm["mandible"]], THICKNESS_CAP / MM) * MM

    parts = {name: _part(name, PV * MM, PF, teeth_colors(name, PV) if name.endswith("_teeth") else None)
             for name, (PV, PF) in parts_mm.items() if not name.startswith("eye")}
    parts["eye_l"] = _part("eye_l", eye_l[0], eye_l[1], eye_l[2])
    parts["eye_r"] = _part("eye_r", eye_r[0], eye_r[1], eye_r[2])
    return FaceModel(
        skin_vertices=np.ascontiguousarray(V * MM, dtype=np.float64),
        skin_faces=np.ascontiguousarray(F, dtype=np.int32),
        skin_uv=skin_uv(V),
        skin_color=SKIN_COLOR.copy(),
        skin_mirror=mirror.astype(np.int32),
        skin_region=region.astype(np.int32),
        region_names=list(REGION_NAMES),
        skin_thickness=thickness.astype(np.float64),
        layer_params={"layer_depth_fractions": list(LAYER_DEPTH_FRACTIONS)},
        parts=parts,
        jaw_pivot=S.JAW_PIVOT * MM,
        jaw_axis=np.array([1.0, 0.0, 0.0]),
        eye_centers={"eye_l": S.EYE_CENTER * MM, "eye_r": eye_r_center * MM},
        feature_points=feature_points,
        muscles=muscles,
        face_def_tables=[],
        fap_mapping={},
        scan_transform=np.eye(4),
        meta={"name": "generic_head", "generator": "tools/build_template.py", "fae_version": __version__,
              "units": "metres", "description": "fae generic anatomical head (MPEG-4 neutral face)"},
    )
