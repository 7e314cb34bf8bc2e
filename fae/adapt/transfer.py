"""Personalize a FaceModel: fit its skin to a scan and carry the anatomy over (paper 000 §6.2).

- skin: the fitted surface on the template's vertices, so regions, mirror, uv, FDPs and
  muscle ends, all stored as triangle + barycentric coordinates, carry over unchanged; its
  faces are the template's but for caps the fit made in the upper lids, which are flipped
  where no surface point binds (fitted_caps_flipped); skin no scanner
  sees (visible_skin: inside the mouth, between the lips, the eye sockets) gets no scan
  target and follows its neighbours; feature points that would fold the skin (inner lip
  points of a scan with the mouth open) are ignored and reported;
- cranium, mandible: through interior_field, a global biharmonic RBF through the fitted
  skin's displacement (the local step included, which on a real face moves the skin by
  centimetres at the jaw: the fit's level functions alone would leave the bone outside a
  thinner chin); blended towards the field's quadratic or affine fit over the bone
  wherever that would fold them or make them cut through themselves (carry_bone,
  fae.adapt.untangle), then pushed under the skin where
  the new soft tissue is thinner than MIN_BONE_DEPTH, by pushes spread in space so both
  sides of a thin bone move together (push_under_skin);
- teeth, tongue: rigid (eq. 25-28): moved with interior_field at their centre and scaled
  uniformly by the mouth-width ratio |8.3-8.4|, no rotation (the scan is already
  calibrated into the face frame); where the upper incisors then show less under the upper
  lip than the template's, each row of teeth moves down until its incisors' edge lies as
  far below its lip's inner point as on the template (mouth_parts_at_lips; the tongue with
  the lower row); and back wherever they show through the lips (mouth_parts_behind_lips);
- eyes: fitted into the adapted socket (eye_in_socket: centre and scale by least squares
  on the socket's template gaps, capped so the eyelids are never crossed), no smaller than
  EYE_MIN_SHARE of the eye width's ratio: an eye that would cross its lids moves back, and
  the orbit's hidden skin behind it is pushed back to make room (orbit_yields; a bust's
  sculpted eyes otherwise leave sockets too shallow, and eyeballs shrunk to 0.6 looked lost
  in their openings);
- linear muscles whose line would leave the soft tissue get a nearby bone attachment from
  which it does not (keep_muscles_inside);
- jaw pivot: through interior_field; jaw axis unchanged;
- sphincter semi-axes and linear-muscle fall-off distances: scaled by the mouth-width ratio
  (sphincters near the mouth) or the eye-width ratio (near an eye);
- skin_thickness: recomputed as the distance to the nearest bone, capped at the template's
  largest thickness;
- FaceDefTables: displacements (metres per FAP unit) scaled by the ratio of the mean FAPU
  distance (ES, ENS, MNS, MW) of the new face to the template's, since a FAP moves a point
  by value x FAPU;
- fap_mapping cleared (the runtime re-derives it); scan_transform maps the face frame back
  to the scan's frame and unit; meta["symmetric"] = False (a person is not symmetric; the
  mirror pairing is kept for left/right).

Not done: the template is not subdivided to the scan's resolution (paper 001), since
FDPs, muscles and regions are bound to its triangles; the fitted skin has the template's
resolution.
"""

from __future__ import annotations

import copy
import time
from typing import Callable

import numpy as np

from fae.adapt.calibration import apply_transform, calibration_transform, outlier_landmarks
from fae.adapt.correspondence import grid_sample
from fae.adapt.csrbf import wendland_c2
from fae.adapt.errors import Surface, surface
from fae.adapt.geometry import per_face_normals, per_vertex_normals, within
from fae.adapt.multilevel import fit_template
from fae.adapt.query import MeshQuery
from fae.adapt.rbf import RBF, rbf_interpolant, rbf_weights
from fae.adapt.untangle import edge_crossings, folded_pairs, mesh_edges, untangle
from fae.anatomy.surface_points import markup_positions
from fae.io.facemodel import FaceModel
from fae.linalg import turn_between

MIN_BONE_DEPTH = 0.002  # metres of soft tissue kept between skin and bone
MAX_PUSH = 0.002  # metres a bone vertex may be pushed inwards per round
PUSH_RADIUS = 0.025  # metres over which a push spreads through the bone (12.5 x MAX_PUSH: no fold)
PUSH_TOLERANCE = 1e-4  # metres of missing depth left unpushed
FIELD_SPACING = 0.025  # metres between the skin samples of interior_field (about 400 on a head)


def scan_landmarks_in_face_frame(template_points: dict[str, np.ndarray], scan_landmarks: dict[str, np.ndarray],
                                 scan_V: np.ndarray, scan_F: np.ndarray
                                 ) -> tuple[np.ndarray, str, list[str], dict[str, str], Surface]:
    """Calibrate: (4, 4) scan -> face frame, unit name, names used, ignored name -> reason,
    and the scan in the face frame prepared for the fit's queries (fae.adapt.errors.surface)."""
    ignored: dict[str, str] = {}
    for n in scan_landmarks:
        if n not in template_points:
            ignored[n] = "not a feature point of the template"
    names = [n for n in template_points if n in scan_landmarks]
    if len(names) < 4:
        raise ValueError(f"adapt: need at least 4 feature points shared by scan and template, got {len(names)} "
                         f"({', '.join(names) or 'none'})")
    A = np.array([scan_landmarks[n] for n in names])
    B = np.array([template_points[n] for n in names])
    for n in outlier_landmarks(A, B, names):
        ignored[n] = "disagrees with the other feature points (wrong placement?)"
    names = [n for n in names if n not in ignored]
    T, unit = calibration_transform(np.array([scan_landmarks[n] for n in names]),
                                    np.array([template_points[n] for n in names]))
    width = float(np.max(np.ptp(B, axis=0)))
    scan = surface(apply_transform(T, scan_V), scan_F)
    _, dist, _, _ = scan.query.closest_points(apply_transform(T, np.array([scan_landmarks[n] for n in names])))
    for n, d in zip(list(names), dist):
        if d > max(0.1 * width, 0.01):
            ignored[n] = f"{d * 1000:.1f} mm from the scan surface"
    names = [n for n in names if n not in ignored]
    return T, unit, names, ignored, scan


def interior_field(P: np.ndarray, X: np.ndarray, spacing: float = FIELD_SPACING) -> RBF:
    """The fitted skin's displacement carried into the head: a global biharmonic RBF
    (paper 000 §3.2) through X - P at the template skin vertices P (n, 3) spread every
    `spacing` metres (fae.adapt.correspondence.grid_sample); X (n, 3) is the fitted skin,
    metres. Unlike the fit's level functions (Fit.deformation) it includes the local step,
    which on a real face moves the skin by centimetres at the jaw and chin: bones carried
    by it keep their depth under the new skin, and a global biharmonic field is smooth
    enough not to fold a bone a few millimetres thick."""
    P = np.asarray(P, dtype=np.float64)
    s = grid_sample(P, spacing)
    return rbf_weights(P[s], np.asarray(X, dtype=np.float64)[s] - P[s], "biharmonic")


def carried(field: RBF, X: np.ndarray) -> np.ndarray:
    """(n, 3) metres: template-frame points X (n, 3) moved by `field`."""
    X = np.asarray(X, dtype=np.float64)
    return X + rbf_interpolant(field, X)


def carried_affinely(field: RBF, X: np.ndarray) -> np.ndarray:
    """(n, 3) metres: points X (n, 3) moved by the affine part of `field` only (folds
    nothing while its determinant stays positive)."""
    X = np.asarray(X, dtype=np.float64)
    return X + X @ field.affine[:3] + field.affine[3]


def polynomial_fit(V: np.ndarray, Y: np.ndarray, degree: int) -> np.ndarray:
    """(n, 3): the least-squares polynomial map of `degree` (1: affine, 2: quadratic) in the
    coordinates of V (n, 3) that best takes V to Y (n, 3), evaluated at V."""
    if degree not in (1, 2):
        raise ValueError(f"polynomial_fit: degree 1 or 2, got {degree}")
    centred = V - V.mean(axis=0)
    U = centred / max(float(np.max(np.abs(centred))), 1e-12)  # (unit box: well conditioned)
    columns = [np.ones(len(V))] + [U[:, i] for i in range(3)]
    if degree == 2:
        columns += [U[:, i] * U[:, j] for i in range(3) for j in range(i, 3)]
    A = np.stack(columns, axis=1)
    return A @ np.linalg.lstsq(A, Y, rcond=None)[0]


def _whole_like(V0: np.ndarray, X: np.ndarray, F: np.ndarray, query: MeshQuery) -> bool:
    """Whether bone X (n, 3) has no face turned over against its template shape V0 (n, 3)
    (not even gradually, over many faces), no fold (folded_pairs) and no crossing."""
    n0, n1 = per_face_normals(V0, F), per_face_normals(X, F)
    return (bool(np.all(np.einsum("ij,ij->i", n0, n1) > 0.0)) and len(folded_pairs(V0, X, F)) == 0
            and len(edge_crossings(X, F, query=query)[0]) == 0)


def carry_bone(field: RBF, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n, 3) metres: bone V (n, 3), F (m, 3) moved by `field`; wherever that makes it cut
    through itself or fold against its template shape V, it is blended towards a safe bone:
    the closer of the field's quadratic and affine least-squares fits over this bone
    (quadratic, else affine) that neither folds nor crosses, else the field's global affine
    part (fae.adapt.untangle).
    Why fits over the bone: the mandible's ramus has faces 2-3 cm long, across which a field
    that folds nothing in space still collapses a triangle; blending towards the global
    affine part moved the whole mandible there (the blend's own transition folded those
    faces, and the zone grew round by round) and left it 2-3 cm from the jaw the skin was
    fitted to, the mouth's lining through it. On the marble bust with holes the quadratic
    fit leaves 89 % of the mandible on the field, the rest at most 4.7 mm off it (0.2 mm
    on average); the affine fit 85 %, 8.1 mm (0.6 mm); the global affine part none, 28.5 mm
    (16.7 mm)."""
    F = np.asarray(F, dtype=np.int64)
    V = np.asarray(V, dtype=np.float64)
    X = carried(field, V)
    query = MeshQuery(X, F)
    if len(folded_pairs(V, X, F)) == 0 and len(edge_crossings(X, F, query=query)[0]) == 0:
        return X
    safe = carried_affinely(field, V)
    for degree in (2, 1):
        candidate = polynomial_fit(V, X, degree)
        if _whole_like(V, candidate, F, query):
            safe = candidate
            break
    X, _ = untangle(F, X, safe, reference=V, query=query)
    return X


def smooth_push(V: np.ndarray, push: np.ndarray, at: np.ndarray, radius: float) -> np.ndarray:
    """(n, 3) metres: offsets of all points V (n, 3) from pushes push (k, 3) metres applied at
    V[at] (k,), spread in space: D(x) = sum_j w_j push_j / max(1, sum_j w_j) with Wendland
    weights w_j = phi(|x - V[at_j]| / radius). Points near a pushed one move with it, whichever
    side of a thin bone they lie on, so a push cannot fold the bone; the offsets fade to zero
    `radius` metres away."""
    V = np.asarray(V, dtype=np.float64)
    D = np.zeros_like(V)
    total = np.zeros(len(V))
    for a in range(0, len(at), 256):  # (n, 256) weights at a time
        src = V[at[a:a + 256]]
        d2 = np.sum(V * V, 1)[:, None] + np.sum(src * src, 1)[None, :] - 2.0 * V @ src.T
        w = wendland_c2(np.sqrt(np.maximum(d2, 0.0)) / radius)
        D += w @ push[a:a + 256]
        total += w.sum(axis=1)
    return D / np.maximum(total, 1.0)[:, None]


PUSH_ROUNDS = 10  # of push_under_skin


def push_under_skin(model: FaceModel, part: str, min_depth: float = MIN_BONE_DEPTH, rounds: int = PUSH_ROUNDS,
                    reference: np.ndarray | None = None, skin: Surface | None = None) -> int:
    """Push bone `part` of `model` inwards wherever less than `min_depth` metres of soft
    tissue cover it, or a skin vertex lies inside it (the scanned face is thinner than the
    template's). Each round moves every such bone vertex against the skin normal at its
    closest skin point by what it lacks (at most MAX_PUSH), spread in space over
    PUSH_RADIUS (smooth_push) so that the bone dents smoothly and both of its sides move
    together. Should that still fold the bone against `reference` (its template shape,
    (n, 3); default: the bone before the push), the fold is blended back (untangle).
    skin: surface(model.skin_vertices, model.skin_faces), when already prepared.
    Changes `model` in place; returns how many bone vertices moved."""

    from scipy.spatial import cKDTree

    bone = model.parts[part]
    V = bone.vertices.copy()
    BF = np.asarray(bone.faces, dtype=np.int64)
    if skin is None:
        skin = surface(model.skin_vertices, model.skin_faces)
    S, SF = skin.V, skin.F
    skin_q, skin_n = skin.query, skin.N
    bone_q = MeshQuery(V, BF)
    reach = rounds * MAX_PUSH + min_depth  # bone deeper than this under the skin needs nothing
    inside_reach = 5 * MAX_PUSH  # skin "inside" farther from the bone's surface is a fold of the bone, not skin
    edge = 2.0 * float(np.max(np.linalg.norm(V[BF[:, 1]] - V[BF[:, 0]], axis=1)))  # bone faces stretch under pushes
    depth = np.full(len(V), np.inf)  # > 0: below the skin, along the skin normal there
    normal = np.zeros_like(V)
    stale = np.full(len(V), np.inf)  # how far each bone vertex moved since its depth was measured
    gap = np.full(len(S), np.inf)  # signed distance of each skin vertex to the bone (< 0: inside), when measured
    drift = np.full(len(S), np.inf)  # how far the bone may have moved towards it since
    moved = np.zeros(len(V), dtype=bool)
    for _ in range(rounds):
        redo = np.flatnonzero(stale > 0.5 * PUSH_TOLERANCE)
        depth[redo], normal[redo] = depth_under(skin_q, skin_n, SF, V[redo], reach)
        stale[redo] = 0.0
        bone_q.move(V)
        check = np.flatnonzero(drift >= np.abs(gap))  # skin the bone may have reached or left
        gap[check] = np.minimum(bone_q.signed_distances(S[check], inside_reach), inside_reach)
        drift[check] = 0.0
        inside = gap < 0.0
        need = np.maximum(min_depth - depth, 0.0)
        if np.any(inside):  # skin inside the bone: its nearest bone vertices go below it, and so do
            # the corners of the bone's face it is under (the cranium's faces over the neck are 2 cm
            # across: skin 2.5 mm inside one lay 10 mm from every corner, out of the nearest's reach)
            d, j = cKDTree(V).query(S[inside], distance_upper_bound=inside_reach)
            close = np.isfinite(d)
            np.maximum.at(need, j[close], d[close] + min_depth)
            _, d, face, _ = bone_q.closest_points(S[inside], inside_reach)
            close = face >= 0
            np.maximum.at(need, BF[face[close]].ravel(), np.repeat(d[close] + min_depth, 3))
        need = np.minimum(need, MAX_PUSH)
        at = np.flatnonzero(need > PUSH_TOLERANCE)
        if len(at) == 0:
            break
        D = smooth_push(V, -normal[at] * need[at, None], at, PUSH_RADIUS)
        V += D
        step = np.linalg.norm(D, axis=1)
        stale += step
        moved |= step > 1e-6
        drift[within(S, V[at], PUSH_RADIUS + edge + MAX_PUSH)] += step.max()  # bone within PUSH_RADIUS of a push moved
    bone.vertices, _ = untangle(BF, V, bone.vertices, reference=bone.vertices if reference is None else reference,
                                query=bone_q)
    return int(moved.sum())


HIDDEN_SKIN_MARGIN = 3e-4  # m outside the bone
HIDDEN_SKIN_RADIUS = 0.004  # m
HIDDEN_SKIN_ROUNDS = 4


def hidden_skin_off_bones(template: FaceModel, model: FaceModel, margin: float = HIDDEN_SKIN_MARGIN) -> int:
    """Skin no scanner sees (visible_skin of the template: the sockets behind the eyelids,
    the mouth's lining) that still lies inside the cranium or mandible after the bones
    yielded (push_under_skin gives back what would fold the bone: the thin wall of an orbit
    deepened for a large eye) moves out of it: to `margin` metres outside along the bone's
    normal at its closest point, spread over HIDDEN_SKIN_RADIUS among the hidden skin
    only, so that nothing a viewer sees moves. Changes model.skin_vertices in place;
    returns how many skin vertices moved."""
    X = model.skin_vertices
    hidden = None
    moved = np.zeros(len(X), dtype=bool)
    for name in ("cranium", "mandible"):
        if name not in model.parts:
            continue
        bone = MeshQuery(model.parts[name].vertices, np.asarray(model.parts[name].faces, np.int64))
        for _ in range(HIDDEN_SKIN_ROUNDS):
            depth = -bone.signed_distances(X, HIDDEN_SKIN_RADIUS)  # > 0: inside the bone
            at = np.flatnonzero(np.isfinite(depth) & (depth > 0.0))
            if len(at) == 0:
                break
            if hidden is None:
                hidden = ~visible_skin(template)
            at = at[hidden[at]]
            if len(at) == 0:
                break
            pts = bone.closest_points(X[at], HIDDEN_SKIN_RADIUS)[0]
            out = (pts - X[at]) / np.maximum(np.linalg.norm(pts - X[at], axis=1, keepdims=True), 1e-12)
            D = smooth_push(X, out * (depth[at] + margin)[:, None], at, HIDDEN_SKIN_RADIUS)
            D[~hidden] = 0.0
            X = X + D
            moved |= np.linalg.norm(D, axis=1) > 1e-7
    model.skin_vertices = X
    return int(moved.sum())


LINING_CLEARANCE = 0.001  # m: hidden skin keeps this much (or its template's) behind the visible skin
LINING_REACH = 0.004  # m: hidden skin farther than this from the visible skin is left alone
LINING_PUSH_RADIUS = 0.002  # m over which a push spreads among the hidden skin
LINING_ROUNDS = 3
# Skin regions whose rim moves back too: a sculpted lower lid pressed its rim's lining
# against the lid's front, and as a smile's cheek raised the lid the skin's back showed
# (marble: 2-5 mm^2 at the lower lids in 20 frames of xface_pride, 23 over the nine xface
# streams; 2 with the rim moved). The three busts' folds over the nine streams 80 / 120 /
# 113 -> 77 / 115 / 111. The upper lids' rim moved as well folded Demosthenes' upper lids
# more (68 -> 89 triangles)
LINING_RIM_MOVED_REGIONS = ("eyelid_lower_l", "eyelid_lower_r")


def hidden_skin_behind_visible(template: FaceModel, X: np.ndarray) -> tuple[np.ndarray, int]:
    """The fitted skin X (n, 3) metres (a copy) with its hidden skin (not visible_skin of
    the template, the mouth's lining left out: the lids' lining, the nostrils, the backs
    of the ears), all but its rim beside the visible skin (a lower lid's rim moves too:
    LINING_RIM_MOVED_REGIONS), moved back where the fit brought it nearer the visible skin
    than min(its template clearance, LINING_CLEARANCE), or through it: along its closest
    visible triangle's normal, to the side the template has it on, spread over
    LINING_PUSH_RADIUS among the hidden skin only, and held wherever it would fold a
    triangle or pass an edge through other skin (the rim outside LINING_RIM_MOVED_REGIONS
    and the corners feature points bind to stay where the fit put them). The fit pulls the visible
    skin onto the scan and lets the hidden skin follow its neighbours, so a sculpted lid
    pressed in or a thin nostril wing can leave the lining touching the skin at rest, and
    the slightest motion then brings it out through the skin. Returns the skin and how
    many vertices moved."""
    from fae.adapt.nonrigid import folded_triangles

    P = np.asarray(template.skin_vertices, dtype=np.float64)
    X = np.array(X, dtype=np.float64)
    F = np.asarray(template.skin_faces, dtype=np.int64)
    names = list(template.region_names)
    seen = visible_skin(template)
    hidden = ~seen
    if "mouth_cavity" in names:
        hidden &= np.asarray(template.skin_region) != names.index("mouth_cavity")
    # the rim (hidden skin beside visible skin: a lid's margin) stays: feature points bind
    # to its triangles, and it is where the two meet anyway; so do the corners feature
    # points bind to elsewhere (the upper lids' points lie just inside their margins). Not
    # the lower lids' rim (LINING_RIM_MOVED_REGIONS), but for its feature points' corners
    rim = np.zeros(len(P), dtype=bool)
    mixed = F[seen[F].any(axis=1) & ~seen[F].all(axis=1)]
    rim[mixed.ravel()] = True
    rim &= ~np.isin(np.asarray(template.skin_region),
                    [names.index(r) for r in LINING_RIM_MOVED_REGIONS if r in names])
    for point in template.feature_points.values():  # a lid's point may bind just inside its margin
        if point.part == "skin":
            rim[F[point.triangle][np.asarray(point.bary) > 0.0]] = True
    hidden &= ~rim
    shown = F[seen[F].all(axis=1)]  # triangles with every corner visible
    edges = mesh_edges(F)
    at = np.flatnonzero(hidden)
    if len(at) == 0 or len(shown) == 0:
        return X, 0
    near_P, clearance, tri_P, _ = MeshQuery(P, shown).closest_points(P[at], LINING_REACH)
    want = np.where(tri_P >= 0, np.minimum(clearance, LINING_CLEARANCE), 0.0)
    # which side of the visible skin each lies on, from the template: the side of its
    # closest visible triangle's normal (a fit may have pressed it flat against, or through)
    side = np.sign(np.einsum("ij,ij->i", P[at] - near_P, per_face_normals(P, shown)[np.maximum(tri_P, 0)]))
    moved = np.zeros(len(X), dtype=bool)
    for _ in range(LINING_ROUNDS):
        near, _, tri, _ = MeshQuery(X, shown).closest_points(X[at], LINING_REACH)
        away = side[:, None] * per_face_normals(X, shown)[np.maximum(tri, 0)]
        gap = np.einsum("ij,ij->i", X[at] - near, away)  # signed: < 0 through the skin
        need = np.where((tri >= 0) & (tri_P >= 0), want - gap, 0.0)
        push = need > 1e-5
        if not push.any():
            break
        D = smooth_push(X, away[push] * need[push, None], at[push], LINING_PUSH_RADIUS)
        D[~hidden] = 0.0
        # held wherever it would fold a triangle or pass an edge through other skin (what the
        # fit left so is not this push's doing)
        folded = folded_triangles(P, X, F)
        query = MeshQuery(X, F)
        crossing = query.edge_crossings(edges) >= 0
        for _ in range(8):
            query.move(X + D)
            through = query.edge_crossings(edges)
            new_edges = (through >= 0) & ~crossing
            new = folded_triangles(P, X + D, F) & ~folded
            if not new.any() and not new_edges.any():
                break
            D[F[new].ravel()] = 0.0
            D[edges[new_edges].ravel()] = 0.0
            D[F[through[new_edges]].ravel()] = 0.0
        else:  # still not clean: this round moves nothing
            D[:] = 0.0
        moved |= np.linalg.norm(D, axis=1) > 1e-7
        X = X + D
    return X, int(moved.sum())


def depth_under(skin_q: MeshQuery, skin_n: np.ndarray, skin_F: np.ndarray, X: np.ndarray, reach: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Depth (k,) metres of points X (k, 3) under the skin along the skin's normal at their
    closest skin point (> 0: below it; inf: no skin within `reach` metres), and that unit
    normal (k, 3). skin_q: the skin's MeshQuery, skin_n (n, 3) its vertex normals."""
    pts, _, face, bary = skin_q.closest_points(X, reach)
    ok = face >= 0
    n = np.zeros_like(X)
    n[ok] = np.einsum("nk,nkd->nd", bary[ok], skin_n[skin_F[face[ok]]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return np.where(ok, np.sum((pts - X) * n, axis=1), np.inf), n


def visible_skin(model: FaceModel, offset: float = 1e-4) -> np.ndarray:
    """(V,) bool: skin vertices a scanner can see, i.e. whose outward normal ray (from
    `offset` metres above the skin) meets neither the skin nor an eyeball. False inside the
    mouth, between the lips, on the eye sockets behind the eyelids and inside the nostrils;
    those vertices get no scan target and follow their neighbours."""
    V, F = model.skin_vertices, model.skin_faces.astype(np.int64)
    meshes = [(V, F)] + [model.mesh(n) for n in ("eye_l", "eye_r") if n in model.parts]
    allV, allF, base = [], [], 0
    for mv, mf in meshes:
        allV.append(np.asarray(mv, dtype=np.float64))
        allF.append(np.asarray(mf, dtype=np.int64) + base)
        base += len(mv)
    q = MeshQuery(np.vstack(allV), np.vstack(allF))
    N = per_vertex_normals(V, F)
    hit, _, _, _ = q.ray_hits(V + offset * N, N, 1.0)
    return ~hit


EYE_SOCKET_REACH = 0.004  # m: skin this close to the template's eyeball forms its socket
EYE_MIN_GAP_SHARE = 0.5  # of each socket vertex's template gap kept between it and the eyeball


def eye_socket(template: FaceModel, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The template's eyeball `name` and the skin around it: centre c0 (3,) metres, the
    eyeball's vertices EV (k, 3), their distances r_eye (k,) from c0, and each skin
    vertex's gap (n,) metres from the eyeball's median radius (< 0 inside it)."""
    c0 = np.asarray(template.eye_centers[name], dtype=np.float64)
    EV = template.parts[name].vertices
    r_eye = np.linalg.norm(EV - c0, axis=1)
    gap = np.linalg.norm(template.skin_vertices - c0, axis=1) - float(np.median(r_eye))
    return c0, EV, r_eye, gap


def eye_in_socket(template: FaceModel, model: FaceModel, name: str) -> tuple[np.ndarray, float]:
    """Centre (3,) metres and uniform scale of eyeball `name` fitted into the adapted socket.

    The socket is the template skin within EYE_SOCKET_REACH of the eyeball (eyelids and
    the orbit behind them), with gaps g_i = |x_i - c0| - r0 to the template's eyeball
    (centre c0, radius r0). On the adapted skin (positions y_i) the centre c and radius R
    minimize sum (|y_i - c| - R - g_i)^2 (paper 000 eq. 25-28 move the eye with the
    deformation; a fit to the socket keeps the eyelids on the eyeball). The scale R / r0
    is then capped so that every socket vertex keeps EYE_MIN_GAP_SHARE of its gap from the
    eyeball's surface in its direction: the eyeball never pokes through the eyelids.
    """
    from scipy.optimize import least_squares

    c0, EV, r_eye, gap = eye_socket(template, name)
    r0 = float(np.median(r_eye))
    socket = np.flatnonzero((gap > 0) & (gap < EYE_SOCKET_REACH))
    c_start = np.asarray(model.eye_centers[name], dtype=np.float64)
    if len(socket) < 10:
        return c_start, 1.0
    Y, g = model.skin_vertices[socket], gap[socket]

    def residual(x):
        return np.linalg.norm(Y - x[:3], axis=1) - x[3] - g

    sol = least_squares(residual, np.append(c_start, r0), x_scale=np.full(4, 1e-3))
    c, R = sol.x[:3], float(sol.x[3])
    # the eyeball's radius towards each socket vertex (the cornea bulges in front)
    from scipy.spatial import cKDTree

    d = Y - c
    room = np.linalg.norm(d, axis=1)
    toward = cKDTree((EV - c0) / r_eye[:, None]).query(d / room[:, None])[1]
    limit = float(np.min((room - EYE_MIN_GAP_SHARE * g) / r_eye[toward]))
    return c, float(min(R / r0, limit))


def orbit_yields(template: FaceModel, model: FaceModel, name: str, c: np.ndarray, s: float,
                 rounds: int = 8) -> bool:
    """Deepen the orbit of eyeball `name` (centre c (3,) metres, scale s) where the eyeball
    crosses it: the socket skin behind the eye's equator (the template skin within
    EYE_SOCKET_REACH of the eyeball, facing it from behind; no scanner sees it) is pushed
    away from the centre until it keeps EYE_MIN_GAP_SHARE of its template gap, spread
    over ORBIT_PUSH_RADIUS (smooth_push). A scan whose lids lie on a sculpted or shut eye
    leaves a socket too shallow for the eyeball; shrinking the eye instead shows it lost in
    its opening. Changes model.skin_vertices in place; returns whether any moved."""
    from scipy.spatial import cKDTree

    c0, EV, r_eye, gap = eye_socket(template, name)
    behind = (template.skin_vertices - c0)[:, 2] < 0.0
    socket = np.flatnonzero((gap > 0) & (gap < EYE_SOCKET_REACH) & behind)
    if len(socket) == 0:
        return False
    directions = cKDTree((EV - c0) / r_eye[:, None])
    X = model.skin_vertices
    moved = False
    for _ in range(rounds):
        d = X[socket] - c
        room = np.linalg.norm(d, axis=1)
        u = d / np.maximum(room, 1e-12)[:, None]
        need = s * r_eye[directions.query(u)[1]] + EYE_MIN_GAP_SHARE * gap[socket] - room
        at = need > 1e-5
        if not at.any():
            break
        X = X + smooth_push(X, u[at] * need[at, None], socket[at], ORBIT_PUSH_RADIUS)
        moved = True
    model.skin_vertices = X
    return moved


# each eye's opening: its lids' (upper, lower) and corners' (inner, outer) feature points.
# The eye looks through the opening's middle, as the template's does; a turn of its rest
# gaze by up to EYE_MAX_GAZE_TURN gets it there
EYE_OPENINGS = {"eye_l": ("3.1", "3.3", "3.11", "3.7"), "eye_r": ("3.2", "3.4", "3.12", "3.8")}
EYE_MAX_GAZE_TURN = np.radians(10.0)


def opening_middle(fp: dict, name: str) -> np.ndarray | None:
    """(3,) metres: the middle of eye `name`'s opening from feature point positions `fp`:
    across the face between its corners, up and down and in depth between its lids' middles
    (a fit can leave the lids' points a few millimetres apart across the face), or None
    without them."""
    points = EYE_OPENINGS.get(name)
    if points is None or not all(p in fp for p in points):
        return None
    upper, lower, inner, outer = (np.asarray(fp[p], dtype=np.float64) for p in points)
    lids = 0.5 * (upper + lower)
    return np.array([0.5 * (inner[0] + outer[0]), lids[1], lids[2]])


def gaze_turn(template: FaceModel, model: FaceModel, name: str, c: np.ndarray) -> np.ndarray:
    """(3, 3) rotation about eyeball `name`'s centre c (3,) metres on the adapted `model`
    that turns the template's rest gaze (from its eye centre through its opening's middle)
    through the middle of the adapted opening, by at most EYE_MAX_GAZE_TURN.

    The socket fit places the eyeball in the orbit; a scan's lids open where the person's
    do, which need not be where the template's sit on the eyeball (the busts' openings are
    narrower and their middles lay 1.4-1.9 mm below their eyes' centres: the irises showed
    high, half under the upper lids). Turned, the eye looks out of the opening's middle;
    its centre and the socket's fit stay."""
    before = opening_middle(template.feature_point_positions(), name)
    after = opening_middle(model.feature_point_positions(), name)
    if before is None or after is None:
        return np.eye(3)
    return turn_between(before - np.asarray(template.eye_centers[name], dtype=np.float64),
                        after - np.asarray(c, dtype=np.float64), EYE_MAX_GAZE_TURN)


LID_GAP_WARNED = 0.003  # m: an upper lid farther off its eyeball than this is told of (fae adapt)


def lid_gaps(model: FaceModel) -> dict[str, dict[str, float]]:
    """{eye: {"upper": m, "lower": m}}: how far the middle of each eye's lids (their
    feature points, EYE_OPENINGS) lies from the eyeball's surface, metres; the template's
    lie 0.8 mm off. A lid far off its eyeball stands in front of it: seen from the side,
    the eye sits deep behind a thick rim (the busts' sculpted upper lids 5-10 mm off)."""
    fp = model.feature_point_positions()
    out = {}
    for name, (upper, lower, _, _) in EYE_OPENINGS.items():
        if name not in model.parts or upper not in fp or lower not in fp:
            continue
        V, F = model.mesh(name)
        d = MeshQuery(np.asarray(V, np.float64), np.asarray(F, np.int64)).closest_points(
            np.array([fp[upper], fp[lower]], dtype=np.float64), 1.0)[1]
        out[name] = {"upper": float(d[0]), "lower": float(d[1])}
    return out


ORBIT_PUSH_RADIUS = 0.004  # m over which a push deepening an orbit takes the skin around along
EYE_MIN_SHARE = 0.9  # of the ratio of the outer eye corners' distance: no eyeball is scaled below this
EYE_SINK_STEP = 0.0005  # m: an eyeball that crosses the skin moves away from it by this much at a time
EYE_MAX_SINK_STEPS = 12

MUSCLE_SEARCH_RADIUS = 0.035  # m: how far a linear muscle's attachment may move on its bone
MUSCLE_MARGIN = 2e-4  # m: a muscle's line keeps this far inside the skin


MOUTH_PARTS = ("upper_teeth", "lower_teeth", "tongue")
MOUTH_SCALE_SPREAD = 0.05  # teeth and tongue scale within 5 % of the face's scale (busts: 0-4 %)
MOUTH_SINK_STEP = 0.0005  # m: teeth or tongue that show through the lips move back this much at a time
MOUTH_MAX_SINK_STEPS = 30
MOUTH_POKE_REACH = 0.006  # m behind a tooth where the skin it pokes through is looked for
MOUTH_MIN_SHIFT = 0.0005  # m: teeth within this of the template's place under the lips stay (mouth_parts_at_lips)
MOUTH_MAX_SHIFT = 0.01  # m: and move at most this far down to it


def teeth_through_skin(model: FaceModel, skin: MeshQuery, X: np.ndarray) -> np.ndarray:
    """(n,) bool: points X (n, 3) of teeth or tongue that show through the skin from the
    front: nothing lies in front of them (+z), and just behind them (within
    MOUTH_POKE_REACH) is outer skin facing forwards, not the mouth's lining: a tooth in
    front of the lips or the chin. Teeth seen through the parted lips have the mouth behind
    them instead; teeth behind closed lips have the lips in front."""
    from fae.mesh import triangle_normals

    F = np.asarray(model.skin_faces, np.int64)
    normal_z = triangle_normals(model.skin_vertices, F)[:, 2]
    names = list(model.region_names)
    lining = np.zeros(len(F), dtype=bool)
    if "mouth_cavity" in names:
        lining = (np.asarray(model.skin_region)[F] == names.index("mouth_cavity")).any(axis=1)
    ahead, _, _, _ = skin.ray_hits(X, np.tile([0.0, 0.0, 1.0], (len(X), 1)), 1.0)
    behind, t, face, _ = skin.ray_hits(X, np.tile([0.0, 0.0, -1.0], (len(X), 1)), MOUTH_POKE_REACH)
    face = np.maximum(face, 0)
    return ~ahead & behind & (t < MOUTH_POKE_REACH) & (normal_z[face] > 0.0) & ~lining[face]


# each row of teeth, its incisors' edge (the feature point on it: 9.10 the upper row's
# bottom, 9.11 the lower row's top), its lip's inner point, and the parts that move with it
TEETH_ROWS = (("upper_teeth", "9.10", "2.2", ("upper_teeth",)), ("lower_teeth", "9.11", "2.3", ("lower_teeth", "tongue")))


def mouth_parts_at_lips(template: FaceModel, model: FaceModel, scale: float) -> dict[str, float]:
    """Where the upper incisors show less below the upper lip than the template's (by more
    than MOUTH_MIN_SHIFT), move each row of teeth down (y, rigidly; the tongue with the
    lower row) until its incisors' edge (9.10, 9.11) lies as far below its lip's inner point
    (2.2 for the upper row, 2.3 for the lower) as on the template, that distance times
    `scale` (the mouth's), by at most MOUTH_MAX_SHIFT: the upper incisors show under the
    upper lip as the template's do, and lips that meet put the rows in the template's bite.
    Carried by the interior field alone, the teeth follow the skin around the mouth as a
    whole, not the lips, and each row its own way: the marble bust's upper incisors stood
    2.6 mm above its upper lip's inner point (the template's 2.7 mm below it), 2.5 mm above
    the lower row's edge, and its smile showed no teeth, only the mouth's dark. Teeth that
    show as much or more stay, and no row moves up: a photo smiling with parted lips has
    them filling the gap, where the lips' rest says nothing of the bite. Changes `model` in
    place; returns part -> metres moved down (empty: none moved)."""
    old, new = template.feature_point_positions(), model.feature_point_positions()
    down = {}
    for row, edge, lip, _ in TEETH_ROWS:
        if all(n in old and n in new for n in (edge, lip)) and row in model.parts:
            wanted = new[lip][1] - (old[lip][1] - old[edge][1]) * scale
            down[row] = float(np.clip(new[edge][1] - wanted, 0.0, MOUTH_MAX_SHIFT))
    if not down.get("upper_teeth", 0.0) > MOUTH_MIN_SHIFT:  # (NaN: a point or scale unknown)
        return {}
    moved = {}
    for row, _, _, parts in TEETH_ROWS:
        for name in parts:
            if name in model.parts and np.isfinite(down.get(row, np.nan)):
                model.parts[name].vertices = model.parts[name].vertices - np.array([0.0, down[row], 0.0])
                moved[name] = down[row]
    return moved


def mouth_parts_behind_lips(model: FaceModel, skin: MeshQuery) -> dict[str, float]:
    """Move teeth and tongue back (-z, rigidly, MOUTH_SINK_STEP at a time) while any of
    their vertices shows through the skin (teeth_through_skin): a fit that widened the
    mouth or moved the lips (a smile on a photo) would otherwise leave teeth in front of
    the lips or the chin. Returns part -> metres moved (the parts that moved)."""
    moved = {}
    for name in MOUTH_PARTS:
        if name not in model.parts:
            continue
        part = model.parts[name]
        step = 0
        while step < MOUTH_MAX_SINK_STEPS and teeth_through_skin(model, skin, part.vertices).any():
            part.vertices = part.vertices - np.array([0.0, 0.0, MOUTH_SINK_STEP])
            step += 1
        if step:
            moved[name] = step * MOUTH_SINK_STEP
    return moved


def keep_muscles_inside(model: FaceModel, skin: MeshQuery | None = None) -> list[str]:
    """Move the bone attachment of every linear muscle whose line leaves the soft tissue of
    `model` (skin changed, bones did not follow exactly) to the nearest bone vertex, within
    MUSCLE_SEARCH_RADIUS (else twice that), from which the line to its (unchanged) skin
    insertion stays inside the skin by MUSCLE_MARGIN (else at all; skin: its MeshQuery,
    when already built). Changes `model` in place; returns
    the names of the muscles moved."""
    from fae.io.facemodel import SurfacePoint

    q = MeshQuery(model.skin_vertices, model.skin_faces) if skin is None else skin
    ts = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
    linear = [m for m in model.muscles if m.kind == "linear" and m.insertion is not None]
    if not linear:
        return []
    ends = np.array([[model.surface_point_position(m.attachment), model.surface_point_position(m.insertion)]
                     for m in linear])  # (k, 2, 3)
    samples = ends[:, :1] + ts[None, :, None] * (ends[:, 1:] - ends[:, :1])  # (k, 5, 3)
    # inside by a margin: a line that grazes the skin from within is outside to other tests
    inside = (q.signed_distances(samples.reshape(-1, 3)) < -MUSCLE_MARGIN).reshape(len(linear), len(ts)).all(axis=1)
    moved = []
    for mus, (a, b), ok_now in zip(linear, ends, inside):
        if ok_now:
            continue
        BV, BF = model.mesh(mus.attachment.part)
        # the nearest bone vertex whose line stays inside by the margin; failing that, one
        # whose line stays inside at all; then the same twice as far (a thin cheek wall
        # beside the mouth's cavity leaves the buccinator little room)
        near = np.flatnonzero(np.linalg.norm(BV - a, axis=1) <= 2.0 * MUSCLE_SEARCH_RADIUS)
        near = near[np.argsort(np.linalg.norm(BV[near] - a, axis=1))]
        lines = BV[near][:, None, :] + ts[None, :, None] * (b - BV[near])[:, None, :]
        depth = q.signed_distances(lines.reshape(-1, 3)).reshape(len(near), len(ts)).max(axis=1)
        within = np.linalg.norm(BV[near] - a, axis=1) <= MUSCLE_SEARCH_RADIUS
        for ok in (within & (depth < -MUSCLE_MARGIN), within & (depth < 0.0), depth < -MUSCLE_MARGIN, depth < 0.0):
            if np.any(ok):
                v = int(near[np.argmax(ok)])
                tri = int(np.flatnonzero((BF == v).any(axis=1))[0])
                mus.attachment = SurfacePoint(mus.attachment.part, tri, (np.asarray(BF[tri]) == v).astype(np.float64))
                moved.append(mus.name)
                break
    return moved


def _ratio(a: dict, b: dict, p: str, q: str) -> float | None:
    if p in a and q in a and p in b and q in b:
        d0 = np.linalg.norm(a[p] - a[q])
        if d0 > 0:
            return float(np.linalg.norm(b[p] - b[q]) / d0)
    return None


def adapt_facemodel(template: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray,
                    scan_landmarks: dict[str, np.ndarray], method: str = "multilevel", levels: int = 1,
                    progress: Callable[[str], None] | None = None) -> tuple[FaceModel, dict]:
    """A personalized copy of `template` fitted to the scan (V (n, 3), F (m, 3) in the scan's
    frame and unit; landmarks FDP name -> (3,) in the same) by one of the paper methods of
    fae.adapt.multilevel. Returns (model, report dict)."""
    t0 = time.perf_counter()
    skin_fdp = {n: p for n, p in markup_positions(template).items() if template.feature_points[n].part == "skin"}
    T, unit, names, ignored, scan = scan_landmarks_in_face_frame(skin_fdp, scan_landmarks, scan_V, scan_F)
    PL = np.array([skin_fdp[n] for n in names])
    QL = apply_transform(T, np.array([scan_landmarks[n] for n in names]))
    fit = fit_template(template.skin_vertices, template.skin_faces, PL, scan.V, scan.F, QL, method=method,
                       levels=levels, progress=progress, movable=visible_skin(template), scan=scan)
    for i in fit.dropped_landmarks:
        ignored[names[i]] = "folds the skin (mouth or eyes open on the scan, closed on the template?)"
    names = [n for i, n in enumerate(names) if i not in fit.dropped_landmarks]
    model, report = personalize(template, fit.vertices, T, unit, method)
    report.update({"landmarks_used": names, "ignored_landmarks": ignored, "levels": fit.levels,
                   "chosen_level": fit.chosen_level, "final": dict(fit.final)})
    report["final"]["seconds"] = time.perf_counter() - t0
    return model, report


def personalize(template: FaceModel, skin: np.ndarray, T: np.ndarray, unit: str, method: str
                ) -> tuple[FaceModel, dict]:
    """A copy of `template` whose skin is `skin` (n, 3) metres, fitted in the face frame,
    with the anatomy carried over (see the module docstring); T (4, 4) maps the scan's
    frame to the face frame. Returns the model and a report of what moved."""
    fdp_old = template.feature_point_positions()
    model = copy.deepcopy(template)
    model.skin_vertices, lining_moved = hidden_skin_behind_visible(template, skin)
    fdp_new = model.feature_point_positions()
    mouth = _ratio(fdp_old, fdp_new, "8.3", "8.4") or 1.0
    # a smile (a photo) or a pout widens the mouth, not the teeth: their scale stays within
    # MOUTH_SCALE_SPREAD of the face's own (the outer eye corners' distance ratio)
    face = _ratio(fdp_old, fdp_new, "3.7", "3.12")
    if face:
        mouth = float(np.clip(mouth, face / (1.0 + MOUTH_SCALE_SPREAD), face * (1.0 + MOUTH_SCALE_SPREAD)))
    eye_l = _ratio(fdp_old, fdp_new, "3.7", "3.11") or mouth
    eye_r = _ratio(fdp_old, fdp_new, "3.8", "3.12") or mouth
    rigid_scale = {"eye_l": eye_l, "eye_r": eye_r, "upper_teeth": mouth, "lower_teeth": mouth, "tongue": mouth}
    field = interior_field(template.skin_vertices, model.skin_vertices)
    for name, part in model.parts.items():
        if name in rigid_scale:
            c_old = template.eye_centers[name] if name in template.eye_centers else part.vertices.mean(axis=0)
            c_new = carried(field, c_old[None])[0]
            part.vertices = (part.vertices - c_old) * rigid_scale[name] + c_new
        else:
            part.vertices = carry_bone(field, part.vertices, part.faces)
    model.eye_centers = {k: carried(field, np.asarray(v)[None])[0] for k, v in template.eye_centers.items()}
    eye_scale = {}
    orbits_deepened = []
    skin = surface(model.skin_vertices, model.skin_faces)  # final from here on, but for orbits deepened
    for name in ("eye_l", "eye_r"):
        if name in model.parts and name in template.eye_centers:
            c, s = eye_in_socket(template, model, name)
            rel = template.parts[name].vertices - template.eye_centers[name]
            # a socket the scan closed (sculpted or shut eyes) would shrink the eye: it keeps
            # at least EYE_MIN_SHARE of the eye's width ratio and moves instead, away from the
            # tissue it crosses (back from the lids, or forward from a shallow orbit)
            s = max(s, EYE_MIN_SHARE * (_ratio(fdp_old, fdp_new, "3.7", "3.8") or rigid_scale[name]))
            rel = rel @ gaze_turn(template, model, name, c).T
            direction = rel / np.linalg.norm(rel, axis=1, keepdims=True)
            # the front of the eye clears the lids the scan gave (its back may cross the orbit's
            # skin, which no one sees: that yields below)
            front = direction[:, 2] > 0.0  # the eye looks along +z in the face frame
            for _ in range(EYE_MAX_SINK_STEPS):
                if not (skin.query.inside(rel * s + c) & front).any():
                    break
                c = c - np.array([0.0, 0.0, EYE_SINK_STEP])
            if orbit_yields(template, model, name, c, s):
                skin = surface(model.skin_vertices, model.skin_faces, skin.query)
                orbits_deepened.append(name)
            for _ in range(EYE_MAX_SINK_STEPS):
                crossing = skin.query.inside(rel * s + c)
                if not crossing.any():
                    break
                away = -direction[crossing].mean(axis=0)
                c = c + EYE_SINK_STEP * away / max(float(np.linalg.norm(away)), 1e-9)
            for _ in range(20):  # the socket fit is least squares: make sure no eyelid is crossed
                if not skin.query.inside(rel * s + c).any():
                    break
                s *= 0.98
            model.parts[name].vertices = rel * s + c
            model.eye_centers[name] = c
            eye_scale[name] = s
    mouth_lowered = mouth_parts_at_lips(template, model, mouth)
    mouth_moved = mouth_parts_behind_lips(model, skin.query)
    model.jaw_pivot = carried(field, np.asarray(template.jaw_pivot)[None])[0]
    pushed = 0
    for name in ("cranium", "mandible"):
        if name not in model.parts:
            continue
        pushed += push_under_skin(model, name, reference=template.parts[name].vertices, skin=skin)
        # an orbit deepened for a large eye can need more rounds than a thin face does
        bone = model.parts[name]
        if MeshQuery(bone.vertices, np.asarray(bone.faces, np.int64)).inside(model.skin_vertices).any():
            pushed += push_under_skin(model, name, rounds=3 * PUSH_ROUNDS, reference=template.parts[name].vertices,
                                      skin=skin)
    lifted = hidden_skin_off_bones(template, model)
    if lifted:  # the bone there yields once more to the skin that left it
        skin = surface(model.skin_vertices, model.skin_faces, skin.query)
        for name in ("cranium", "mandible"):
            if name in model.parts:
                pushed += push_under_skin(model, name, min_depth=HIDDEN_SKIN_MARGIN, rounds=PUSH_ROUNDS,
                                          reference=template.parts[name].vertices, skin=skin)
    # soft-tissue depth: distance to the nearest bone (both bones in one BVH)
    bones = [model.parts[n] for n in ("cranium", "mandible") if n in model.parts]
    if bones:
        cap = float(np.max(template.skin_thickness)) if len(template.skin_thickness) else 1.0
        first = np.cumsum([0] + [len(b.vertices) for b in bones[:-1]])
        both = MeshQuery(np.vstack([b.vertices for b in bones]),
                         np.vstack([np.asarray(b.faces, dtype=np.int64) + o for b, o in zip(bones, first)]))
        model.skin_thickness = np.minimum(both.closest_points(model.skin_vertices, cap)[1], cap)
    for m in model.muscles:
        near_eye = m.kind == "sphincter" and ("oculi" in m.name or "eye" in m.name)
        s = (eye_l + eye_r) / 2 if near_eye else mouth
        if m.semi_axes is not None:
            m.semi_axes = np.asarray(m.semi_axes) * s
        m.fall_start *= s
        m.fall_end *= s
    moved_muscles = keep_muscles_inside(model, skin.query)
    fapu_ratio = _fapu_ratio(fdp_old, model.feature_point_positions())  # eyes, teeth placed
    # tables baked from the template's physics do not describe the new head's (bake it again)
    model.face_def_tables = [t for t in model.face_def_tables if t.source == "authored"]
    for t in model.face_def_tables:
        t.displacements = np.asarray(t.displacements) * fapu_ratio
    model.fap_mapping = {}
    model.scan_transform = np.linalg.inv(T)
    model.meta = dict(template.meta)
    model.meta.update({"generator": "fae adapt", "adapt_method": method, "scan_unit": unit, "symmetric": False})
    model.skin_faces, caps_flipped = fitted_caps_flipped(model)
    report = {"method": method, "scan_unit": unit, "bone_vertices_pushed_under_skin": pushed,
              "fapu_ratio": fapu_ratio, "eye_scale": eye_scale, "orbits_deepened": orbits_deepened,
              "lid_gap_m": lid_gaps(model),
              "mouth_parts_moved_back_m": mouth_moved, "mouth_parts_moved_down_m": mouth_lowered,
              "muscle_attachments_moved": moved_muscles, "hidden_skin_lifted_off_bone": lifted,
              "hidden_skin_moved_behind_visible": lining_moved, "lid_faces_reflipped": caps_flipped}
    return model, report


# The fit bends the upper lids' fine triangles onto a scan's lids, and a bust's sculpted
# lids leave 30-52 caps there (a corner over CAP_ANGLE; the template has 2): a cap's normal
# turns over as the lid closes, and the skin check counts it and its neighbour as a crease.
# Flipped where a flip may, as the template's own are (fae.anatomy.template.
# CAP_FLIPPED_REGIONS, same angle and change; about half of them go), the busts' upper-lid
# folds over the nine xface streams fell from 65 / 82 / 135 to 51 / 36 / 68 (marble,
# wreath, Demosthenes). Not the lower lids (marble's lining then showed in more frames) nor
# the lips (the lower lip folded more).
FIT_CAP_FLIPPED_REGIONS = ("eyelid_upper_l", "eyelid_upper_r")


def bound_skin_faces(model: FaceModel) -> np.ndarray:
    """(F,) bool: skin faces a surface point of `model` binds to (feature points, muscle
    attachments and insertions on the skin): their corners must stay as they are."""
    bound = np.zeros(len(model.skin_faces), dtype=bool)
    points = list(model.feature_points.values())
    points += [p for m in model.muscles for p in (m.attachment, m.insertion) if p is not None]
    for point in points:
        if point.part == "skin":
            bound[point.triangle] = True
    return bound


def fitted_caps_flipped(model: FaceModel) -> tuple[np.ndarray, int]:
    """The skin faces (F, 3) of the fitted `model` with the caps of FIT_CAP_FLIPPED_REGIONS
    flipped where a flip may (fae.anatomy.geometry.flip_caps, the template build's angle and
    change; faces a surface point binds to stay), and how many faces changed. No vertex
    moves."""
    from fae.anatomy.geometry import flip_caps
    from fae.anatomy.template import CAP_ANGLE, CAP_FLIP_CHANGE, MM

    F = np.asarray(model.skin_faces)
    names = list(model.region_names)
    lids = np.isin(np.asarray(model.skin_region), [names.index(r) for r in FIT_CAP_FLIPPED_REGIONS if r in names])
    allowed = (lids[F].sum(axis=1) >= 2) & ~bound_skin_faces(model)
    flipped = flip_caps(model.skin_vertices, F, allowed, cap_angle=CAP_ANGLE, max_change=CAP_FLIP_CHANGE * MM)
    return flipped.astype(F.dtype), int(np.any(flipped != F, axis=1).sum())




def _fapu_ratio(old: dict, new: dict) -> float:
    from fae.mpeg4.fapu import fapu0_from_positions

    try:
        a, b = fapu0_from_positions(old), fapu0_from_positions(new)
    except (KeyError, ValueError):
        return 1.0
    keys = ("ES0", "ENS0", "MNS0", "MW0")
    return float(np.mean([b[k] / a[k] for k in keys]))


def adapt_surface(template_V: np.ndarray, template_F: np.ndarray, template_landmarks: dict[str, np.ndarray],
                  scan_V: np.ndarray, scan_F: np.ndarray, scan_landmarks: dict[str, np.ndarray],
                  method: str = "multilevel", levels: int = 1) -> tuple[np.ndarray, np.ndarray, dict]:
    """Fit a bare template surface (V (n, 3) metres, F, FDP name -> (3,)) to a scan in any
    frame and unit. Returns fitted V (n, 3) in the face frame (metres), the (4, 4) scan ->
    face frame transform, and the report dict."""
    T, unit, names, ignored, scan = scan_landmarks_in_face_frame(template_landmarks, scan_landmarks, scan_V, scan_F)
    fit = fit_template(template_V, template_F, np.array([template_landmarks[n] for n in names]), scan.V, scan.F,
                       apply_transform(T, np.array([scan_landmarks[n] for n in names])), method=method, levels=levels,
                       scan=scan)
    return fit.vertices, T, {"method": method, "scan_unit": unit, "landmarks_used": names,
                             "ignored_landmarks": ignored, "levels": fit.levels, "final": fit.final}
