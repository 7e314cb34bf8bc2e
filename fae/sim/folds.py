"""Fold guard: a skin triangle about to turn over is pulled back towards its rest shape, and
creases are smoothed.

Springs along edges have no say in which way a triangle faces: a triangle squeezed by
muscles until one corner crosses the opposite edge is as happy folded as unfolded, and the
skin creases over itself (dark folds under the lower lip, at the mouth corners and over the
brows). After each substep, every triangle of the epidermis and the middle layer whose area, measured in the
plane across its rest normal carried by its hold, has shrunk below `fold_min_area` of its
rest area (or turned negative: folded) is matched to its rest shape by the best rotation in
that plane (2D shape matching; a rotation in the plane cannot turn the triangle over, unlike
the best rotation in 3D), and its corners are moved towards the matched shape, in the plane
only, by

    beta = min(1, (fold_min_area - area / rest area) / fold_min_area),

zero at the threshold, so that the guard sets in smoothly. A corner shared by several
guarded triangles takes the mean of their moves; a move that reaches a bone ends on it, as
a step does (fae.sim.collision). Up to `fold_passes` passes per substep; after the first,
only triangles and particles next to what the previous pass moved are looked at, and on
the CPU the passes stop at the first that guards nothing (`pass_counts`), so skin far
from folding pays one look at its triangles per substep (the shadow's area, a triple product).
The passes keep lists, not only flags: each particle a pass moves goes on `touched` with
its first move (apply_guard moves those alone), each particle apply_guard moves on a list
of moved particles, and a later pass starts from that list (guard_folds_near,
smooth_creases_near): about 200 of the shipped head's 13,836 particles a pass, where a scan
of every triangle and particle for the flags of a few had cost as much as looking at them
(the guard 49 -> 36 % of a frame's time on expressions.fap).
The guard changes no equilibrium of skin that is not near a fold.

Crease smoothing, in the same passes: a hinge fold shows as a dark line long before
either side has turned over. Each epidermis particle keeps its rest offset from the mean of
its neighbours (its Laplacian coordinate, carried by its hold); where the offset strays by
more than `crease_tolerance` x its mean rest edge (a fold line, a spike), the particle is
moved towards the place that restores it, by the excess over the tolerance (at most all of
it). Both moves of a particle are averaged. The crease move is inelastic: the particle's
velocity against it goes (else the next step pushes the same way again, and a held pose
rocks: the forehead under lowered brows moved up to 1 mm a frame forever).

Strain limits, in the same passes: an epidermis edge (where the skin is seen) stretched
beyond `strain_max` or squeezed below `strain_min` x its rest length is pulled back by half
the excess at each end (each end in its own turn, among its neighbours), so that what a
pull asks of a few edges (a closing lid's front, a mouth corner) spreads over their
neighbours before the skin looks torn. The moves are averaged with the others, so a pass
mends a long band of strained edges only in part: the limits hold loosely.

Lip contact, in the same passes: the particles of the upper and lower lip that face each
other at rest (within fae.sim.build.LIP_PAIR_REACH) are kept in order along the head's up
direction carried by their holds: the lips meet and press, but one does not pass through
the other (pressed hard, the slit's coarse inner walls still can, between the pairs). A
shut upper lid rests on the lower lid's margin the same way (`lid_pairs`), taking the
whole correction itself.

The numpy twin is `fae.sim.reference.ReferenceSolver.guard_folds`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from fae.sim.collision import skull_then_jaw_contact, sphere_contact
from fae.sim.integrate import ParticleStatic

wp.set_module_options({"fast_math": True, "enable_backward": False})


@wp.struct
class GuardedTriangle:
    """An epidermis triangle: its particles, its rest corners in its own rest plane (centred,
    metres, counter-clockwise about `normal`), its unit rest normal, its hold's jaw weight and
    twice its rest area (m^2)."""

    i: int
    j: int
    k: int
    p0: wp.vec2
    p1: wp.vec2
    p2: wp.vec2
    normal: wp.vec3
    jaw: float
    area2: float


def guarded_triangles(q: np.ndarray, triangles: np.ndarray, jaw: np.ndarray) -> np.ndarray:
    """Structured array of `GuardedTriangle` for particle triangles (T, 3) at rest q (P, 3)
    metres, with per-particle jaw weights jaw (P,); degenerate triangles are left out."""
    x = q[triangles]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    keep = area2 > 1e-12
    x, n, area2, triangles = x[keep], n[keep] / area2[keep, None], area2[keep], triangles[keep]
    c = x.mean(axis=1)
    e = x[:, 1] - x[:, 0]
    a = e / np.linalg.norm(e, axis=1, keepdims=True)
    b = np.cross(n, a)
    out = np.zeros(len(triangles), dtype=GuardedTriangle.numpy_dtype())
    out["i"], out["j"], out["k"] = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    for corner, name in enumerate(("p0", "p1", "p2")):
        d = x[:, corner] - c
        out[name] = np.column_stack([np.sum(d * a, axis=1), np.sum(d * b, axis=1)])
    out["normal"] = n
    out["jaw"] = jaw[triangles].mean(axis=1)
    out["area2"] = area2
    return out


@wp.func
def _cross2(u: wp.vec2, v: wp.vec2):
    return u[0] * v[1] - u[1] * v[0]


@wp.func
def _count_move(particle_moves: wp.array(dtype=float), i: int, touched: wp.array(dtype=int),
                pass_counts: wp.array(dtype=int)):
    # one more move of particle i this pass; the first puts it on the list apply_guard reads
    if wp.atomic_add(particle_moves, i, 1.0) == 0.0:
        touched[wp.atomic_add(pass_counts, 1, 1)] = i


@wp.func
def _guard_triangle(particle_q: wp.array(dtype=wp.vec3), tri: GuardedTriangle, R0: wp.mat33, R1: wp.mat33,
                    min_area: float, particle_move: wp.array(dtype=wp.vec3), particle_moves: wp.array(dtype=float),
                    touched: wp.array(dtype=int), pass_counts: wp.array(dtype=int)):
    n = R0 * tri.normal
    if tri.jaw > 0.0:
        n = wp.normalize(n * (1.0 - tri.jaw) + R1 * tri.normal * tri.jaw)
    x0 = particle_q[tri.i]
    x1 = particle_q[tri.j]
    x2 = particle_q[tri.k]
    # twice the signed area of the triangle's shadow on the plane across n
    ratio = wp.dot(wp.cross(x1 - x0, x2 - x0), n) / tri.area2
    if ratio >= min_area:
        return
    c = (x0 + x1 + x2) / 3.0
    e = x1 - x0
    a = e - n * wp.dot(e, n)
    la = wp.length(a)
    if la < 1.0e-12:
        a = wp.cross(n, x2 - x0)
        la = wp.length(a)
        if la < 1.0e-12:
            return
    a = a / la
    b = wp.cross(n, a)
    d0 = x0 - c
    d1 = x1 - c
    d2 = x2 - c
    p0 = wp.vec2(wp.dot(d0, a), wp.dot(d0, b))
    p1 = wp.vec2(wp.dot(d1, a), wp.dot(d1, b))
    p2 = wp.vec2(wp.dot(d2, a), wp.dot(d2, b))
    beta = wp.min(1.0, (min_area - ratio) / min_area)
    # the best rotation in the plane taking the rest corners onto the current ones
    s = _cross2(tri.p0, p0) + _cross2(tri.p1, p1) + _cross2(tri.p2, p2)
    k = wp.dot(tri.p0, p0) + wp.dot(tri.p1, p1) + wp.dot(tri.p2, p2)
    h = wp.sqrt(s * s + k * k)
    cs = 1.0
    sn = 0.0
    if h > 1.0e-20:
        cs = k / h
        sn = s / h
    g0 = wp.vec2(cs * tri.p0[0] - sn * tri.p0[1], sn * tri.p0[0] + cs * tri.p0[1]) - p0
    g1 = wp.vec2(cs * tri.p1[0] - sn * tri.p1[1], sn * tri.p1[0] + cs * tri.p1[1]) - p1
    g2 = wp.vec2(cs * tri.p2[0] - sn * tri.p2[1], sn * tri.p2[0] + cs * tri.p2[1]) - p2
    wp.atomic_add(particle_move, tri.i, (a * g0[0] + b * g0[1]) * beta)
    wp.atomic_add(particle_move, tri.j, (a * g1[0] + b * g1[1]) * beta)
    wp.atomic_add(particle_move, tri.k, (a * g2[0] + b * g2[1]) * beta)
    _count_move(particle_moves, tri.i, touched, pass_counts)
    _count_move(particle_moves, tri.j, touched, pass_counts)
    _count_move(particle_moves, tri.k, touched, pass_counts)
    wp.atomic_add(pass_counts, 0, 1)


@wp.kernel
def guard_folds(particle_q: wp.array(dtype=wp.vec3), triangles: wp.array(dtype=GuardedTriangle),
                bone_rotation: wp.array(dtype=wp.mat33), min_area: float, triangle_count: int, chunk: int,
                particle_move: wp.array(dtype=wp.vec3), particle_moves: wp.array(dtype=float),
                touched: wp.array(dtype=int), pass_counts: wp.array(dtype=int)):
    """A pass over every triangle (a substep's first). pass_counts[0] counts the moves asked
    (triangles guarded here; crease and strain moves, lip pairs in the other kernels),
    pass_counts[1] the particles put on `touched` (see _count_move)."""
    start = wp.tid() * chunk
    R0 = bone_rotation[0]
    R1 = bone_rotation[1]
    for t in range(start, wp.min(start + chunk, triangle_count)):
        _guard_triangle(particle_q, triangles[t], R0, R1, min_area, particle_move, particle_moves, touched,
                        pass_counts)


@wp.kernel
def guard_folds_near(particle_q: wp.array(dtype=wp.vec3), triangles: wp.array(dtype=GuardedTriangle),
                     bone_rotation: wp.array(dtype=wp.mat33), min_area: float, chunk: int,
                     moved: wp.array(dtype=int), moved_counts: wp.array(dtype=int), which: int,
                     particle_moved: wp.array(dtype=int), triangle_start: wp.array(dtype=int),
                     particle_triangles: wp.array(dtype=int),
                     particle_move: wp.array(dtype=wp.vec3), particle_moves: wp.array(dtype=float),
                     touched: wp.array(dtype=int), pass_counts: wp.array(dtype=int)):
    """A later pass: only the triangles with a corner the previous pass moved (the particles
    moved[:moved_counts[which]], flagged in particle_moved; their triangles
    particle_triangles[triangle_start[p]:triangle_start[p + 1]]), each once: from its first
    corner that moved."""
    start = wp.tid() * chunk
    R0 = bone_rotation[0]
    R1 = bone_rotation[1]
    for e in range(start, wp.min(start + chunk, moved_counts[which])):
        p = moved[e]
        for s in range(triangle_start[p], triangle_start[p + 1]):
            tri = triangles[particle_triangles[s]]
            first = tri.k
            if particle_moved[tri.j] != 0:
                first = tri.j
            if particle_moved[tri.i] != 0:
                first = tri.i
            if first == p:
                _guard_triangle(particle_q, tri, R0, R1, min_area, particle_move, particle_moves, touched,
                                pass_counts)


@wp.struct
class CreaseVertex:
    """An epidermis particle's rest shape among its neighbours: its neighbours are
    `neighbours[first:end]`, `delta` (metres) its rest offset from their mean (its Laplacian
    coordinate, in the head frame), `edge` (metres) its mean rest edge length, `jaw` its
    hold's jaw weight."""

    first: int
    end: int
    delta: wp.vec3
    edge: float
    jaw: float


def crease_vertices(q: np.ndarray, particles: np.ndarray, edges: np.ndarray, jaw: np.ndarray,
                    movable: np.ndarray, limited: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(structured array of `CreaseVertex` over all particles (P,), neighbours (N,) int32,
    their rest lengths (N,) float32 metres, 0 where the edge's strain is not limited): for
    each movable particle of `particles` (its layer's ids), its neighbours along the
    particle pairs `edges` (E, 2) of that layer; others get no neighbours. q (P, 3) metres
    at rest, jaw (P,), movable (P,) bool, limited (E,) bool: the edges whose strain
    `smooth_creases` keeps within bounds (None: all)."""
    P = len(q)
    limited = np.ones(len(edges), dtype=bool) if limited is None else np.asarray(limited, dtype=bool)
    pairs = np.concatenate([edges, edges[:, ::-1]]).astype(np.int64)
    limit = np.concatenate([limited, limited])
    keep = movable[pairs[:, 0]] & np.isin(pairs[:, 0], particles)
    pairs, limit = pairs[keep], limit[keep]
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    pairs, limit = pairs[order], limit[order]
    count = np.bincount(pairs[:, 0], minlength=P)
    start = np.concatenate([[0], np.cumsum(count)])
    mean = np.column_stack([np.bincount(pairs[:, 0], weights=q[pairs[:, 1], c], minlength=P) for c in range(3)])
    mean /= np.maximum(count, 1)[:, None]
    length = np.bincount(pairs[:, 0], weights=np.linalg.norm(q[pairs[:, 0]] - q[pairs[:, 1]], axis=1), minlength=P)
    out = np.zeros(P, dtype=CreaseVertex.numpy_dtype())
    out["first"], out["end"] = start[:-1], start[1:]
    out["delta"] = np.where((count > 0)[:, None], q - mean, 0.0)
    out["edge"] = length / np.maximum(count, 1)
    out["jaw"] = jaw
    rest = np.where(limit, np.linalg.norm(q[pairs[:, 0]] - q[pairs[:, 1]], axis=1), 0.0)
    return out, pairs[:, 1].astype(np.int32), rest.astype(np.float32)


@wp.func
def _smooth_crease(i: int, particle_q: wp.array(dtype=wp.vec3), cv: CreaseVertex, neighbours: wp.array(dtype=int),
                   neighbour_rest: wp.array(dtype=float), R0: wp.mat33, R1: wp.mat33, tolerance: float,
                   strain_max: float, strain_min: float, particle_move: wp.array(dtype=wp.vec3),
                   particle_moves: wp.array(dtype=float), touched: wp.array(dtype=int),
                   pass_counts: wp.array(dtype=int), particle_crease: wp.array(dtype=wp.vec3)):
    xi = particle_q[i]
    mean = wp.vec3(0.0, 0.0, 0.0)
    for k in range(cv.first, cv.end):
        xj = particle_q[neighbours[k]]
        mean = mean + xj
        rest_length = neighbour_rest[k]
        if rest_length > 0.0:
            d = xi - xj
            length = wp.length(d)
            over = wp.clamp(length, strain_min * rest_length, strain_max * rest_length) - length
            if over != 0.0 and length > 1.0e-12:
                wp.atomic_add(particle_move, i, d * (0.5 * over / length))
                _count_move(particle_moves, i, touched, pass_counts)
                wp.atomic_add(pass_counts, 0, 1)
    mean = mean / float(cv.end - cv.first)
    rest = R0 * cv.delta * (1.0 - cv.jaw) + R1 * cv.delta * cv.jaw
    err = xi - mean - rest
    excess = wp.length(err) / (tolerance * cv.edge) - 1.0
    if excess <= 0.0:
        return
    crease_move = -err * wp.min(1.0, excess)
    wp.atomic_add(particle_move, i, crease_move)
    _count_move(particle_moves, i, touched, pass_counts)
    wp.atomic_add(pass_counts, 0, 1)
    particle_crease[i] = crease_move  # this particle's own thread alone writes it


@wp.kernel
def smooth_creases(particle_q: wp.array(dtype=wp.vec3), vertices: wp.array(dtype=CreaseVertex),
                   neighbours: wp.array(dtype=int), neighbour_rest: wp.array(dtype=float),
                   bone_rotation: wp.array(dtype=wp.mat33), tolerance: float, strain_max: float,
                   strain_min: float, particle_count: int, chunk: int, particle_move: wp.array(dtype=wp.vec3),
                   particle_moves: wp.array(dtype=float), touched: wp.array(dtype=int),
                   pass_counts: wp.array(dtype=int), particle_crease: wp.array(dtype=wp.vec3)):
    """Each epidermis particle whose offset from its neighbours' mean strays from its rest
    offset (carried by its hold) by more than `tolerance` x its mean rest edge is moved
    towards the place that restores it (a fold line or a spike), and along each of its
    limited edges (rest length > 0) stretched beyond `strain_max` or squeezed below
    `strain_min` x its rest length by half the excess (its neighbour takes the other half
    in its own turn). particle_crease: each particle's crease move (apply_guard takes away
    the velocity that pushed against it). A substep's first pass, over every particle."""
    start = wp.tid() * chunk
    R0 = bone_rotation[0]
    R1 = bone_rotation[1]
    for i in range(start, wp.min(start + chunk, particle_count)):
        cv = vertices[i]
        if cv.end > cv.first:
            _smooth_crease(i, particle_q, cv, neighbours, neighbour_rest, R0, R1, tolerance, strain_max, strain_min,
                           particle_move, particle_moves, touched, pass_counts, particle_crease)


@wp.kernel
def smooth_creases_near(particle_q: wp.array(dtype=wp.vec3), vertices: wp.array(dtype=CreaseVertex),
                        neighbours: wp.array(dtype=int), neighbour_rest: wp.array(dtype=float),
                        bone_rotation: wp.array(dtype=wp.mat33), tolerance: float, strain_max: float,
                        strain_min: float, particle_count: int, chunk: int, moved: wp.array(dtype=int),
                        moved_counts: wp.array(dtype=int), which: int, particle_moved: wp.array(dtype=int),
                        particle_move: wp.array(dtype=wp.vec3), particle_moves: wp.array(dtype=float),
                        touched: wp.array(dtype=int), pass_counts: wp.array(dtype=int),
                        particle_crease: wp.array(dtype=wp.vec3)):
    """smooth_creases in a later pass: only the particles the previous pass moved
    (moved[:moved_counts[which]]) and their neighbours, each once: from the lowest-numbered
    of itself and its neighbours that moved. (That needs each edge once and the neighbour
    relation symmetric among movable particles, as crease_vertices makes it from the
    unique edges of a layer: a moved particle is movable, so its rows list every edge.)"""
    start = wp.tid() * chunk
    R0 = bone_rotation[0]
    R1 = bone_rotation[1]
    for e in range(start, wp.min(start + chunk, moved_counts[which])):
        p = moved[e]
        if p >= particle_count:
            continue  # not of the epidermis: no crease of its own, no neighbour there
        near = vertices[p]
        for k in range(near.first - 1, near.end):
            i = p
            if k >= near.first:
                i = neighbours[k]
            cv = vertices[i]
            if cv.end == cv.first:
                continue
            lowest = i  # (i moved or one of its neighbours did: p)
            if particle_moved[i] == 0:
                lowest = p
            for m in range(cv.first, cv.end):
                j = neighbours[m]
                if j < lowest and particle_moved[j] != 0:
                    lowest = j
            if lowest == p:
                _smooth_crease(i, particle_q, cv, neighbours, neighbour_rest, R0, R1, tolerance, strain_max,
                               strain_min, particle_move, particle_moves, touched, pass_counts, particle_crease)


@wp.struct
class LipPair:
    """A particle of the upper lip and the nearest of the lower lip at rest (epidermis), the
    jaw weight of their holds (mean), the least height (metres) of the upper over the
    lower along the head's up direction carried by that hold: the lips' clearance
    (fae.sim.build.LIP_CLEARANCE) or the rest height where less (negative where the upper
    lies lower at rest; a lid's lining 0 at most; a closing lid's, the lower lid's margin
    at its own x, fae.sim.folds.lid_pairs), and the most (+inf for the lips, which part
    freely; an upper lid's margin keeps its lining within a little of its rest height over
    the front), and the share of a correction the upper particle takes (the lower takes the
    rest: half each for the lips; all of it for a closing lid, which stops on the lower lid
    without pushing it down)."""

    upper: int
    lower: int
    jaw: float
    gap: float
    most: float
    upper_share: float


def lip_pairs(q: np.ndarray, upper: np.ndarray, lower: np.ndarray, jaw: np.ndarray, reach: float,
              most_slack: float | None = None, neighbours: int = 1, clearance: float = 0.0) -> np.ndarray:
    """Structured array of `LipPair`: each particle of `upper` (ids) within `reach` metres of
    one of `lower` at rest q (P, 3), with its `neighbours` nearest within it, and each of
    `lower` likewise; with `most_slack` (metres), the upper rises at most that much above
    its rest height over the lower (else without limit). clearance (metres): the least
    height of an upper over a lower particle that lay higher at rest (at most its rest
    height): pairs keep points apart, and the other lip's surface between its particles
    slopes, so particles pressed level can still leave one poking through it."""
    from scipy.spatial import cKDTree

    out = []
    if len(upper) and len(lower):
        for a, b, flip in ((upper, lower, False), (lower, upper, True)):
            d, j = cKDTree(q[b]).query(q[a], k=neighbours)
            d, j = d.reshape(len(a), -1), j.reshape(len(a), -1)
            near = d < reach
            ia, jb = np.broadcast_to(a[:, None], d.shape)[near], b[j[near]]  # (missing neighbours: d inf)
            pu, pl = (jb, ia) if flip else (ia, jb)
            out.append(np.column_stack([pu, pl]))
    pairs = np.unique(np.concatenate(out), axis=0) if out else np.zeros((0, 2), dtype=np.int64)
    rec = np.zeros(len(pairs), dtype=LipPair.numpy_dtype())
    rec["upper"], rec["lower"] = pairs[:, 0], pairs[:, 1]
    rec["jaw"] = 0.5 * (jaw[pairs[:, 0]] + jaw[pairs[:, 1]])
    rec["gap"] = np.minimum(clearance, q[pairs[:, 0], 1] - q[pairs[:, 1], 1])
    rec["most"] = np.inf if most_slack is None else np.maximum(0.0, q[pairs[:, 0], 1] - q[pairs[:, 1], 1]) + most_slack
    rec["upper_share"] = 0.5
    return rec


def lid_pairs(upper: np.ndarray, upper_rest: np.ndarray, lower: np.ndarray, lower_rest: np.ndarray,
              jaw: np.ndarray) -> np.ndarray:
    """Structured array of `LipPair`: each particle of `upper` (ids (k,): an upper lid's skin
    near its margin, at rest upper_rest (k, 3) metres) with the two points of the lower lid's
    margin (particle ids `lower` (m,), -1 where not simulated, at rest lower_rest (m, 3),
    sorted by x) on either side of it across the face (x), its least height over each the
    margin's height at the particle's own x (straight between the two) relative to that
    partner (the rest height, where less): a shut lid's margin lies along the lower lid's
    edges, not on a staircase of their corners. Pairs with a partner not simulated are left
    out (the heights come from the whole margin all the same). The upper particle takes
    each correction (a closing lid stops on the lower lid without pushing it down). jaw (P,):
    the particles' jaw weights.

    The lids are 10 mm apart at rest, too far for `lip_pairs`' reach: a closing lid's margin
    ran past the lower lid's by up to 3 mm, in front of it, and the two cut each other in a
    jagged dark line across the shut eye."""
    if len(upper) == 0 or len(lower) == 0:
        return np.zeros(0, dtype=LipPair.numpy_dtype())
    x = lower_rest[:, 0]
    at = np.searchsorted(x, upper_rest[:, 0])
    sides = np.concatenate([np.maximum(at - 1, 0), np.minimum(at, len(x) - 1)])
    edge_y = np.tile(np.interp(upper_rest[:, 0], x, lower_rest[:, 1]), 2)
    up_y = np.tile(upper_rest[:, 1], 2)
    gap = np.minimum(edge_y, up_y) - lower_rest[sides, 1]
    pu, pl = np.tile(upper, 2), lower[sides]
    keep = pl >= 0
    pairs, first = np.unique(np.column_stack([pu[keep], pl[keep]]), axis=0, return_index=True)
    rec = np.zeros(len(pairs), dtype=LipPair.numpy_dtype())
    rec["upper"], rec["lower"] = pairs[:, 0], pairs[:, 1]
    rec["jaw"] = 0.5 * (jaw[pairs[:, 0]] + jaw[pairs[:, 1]])
    rec["gap"] = gap[keep][first]
    rec["most"] = np.inf
    rec["upper_share"] = 1.0
    return rec


@wp.kernel
def separate_lips(particle_q: wp.array(dtype=wp.vec3), pairs: wp.array(dtype=LipPair),
                  bone_rotation: wp.array(dtype=wp.mat33), pair_count: int,
                  particle_move: wp.array(dtype=wp.vec3), particle_moves: wp.array(dtype=float),
                  touched: wp.array(dtype=int), pass_counts: wp.array(dtype=int)):
    """Lips meet and press but do not pass: an upper-lip particle that has sunk below its
    lower-lip partner (along the head's up direction carried by their holds) and the partner
    are moved apart by the overlap; a pair with a most height (an upper lid's lining over its
    front's margin: fae.sim.build) is drawn together by the excess when the upper rises
    beyond it. The upper particle moves by its share of it (`LipPair.upper_share`: half for
    the lips, all of it for a lid on the lower lid), the lower by the rest."""
    k = wp.tid()
    if k >= pair_count:
        return
    pair = pairs[k]
    y = wp.vec3(0.0, 1.0, 0.0)
    up = wp.normalize(bone_rotation[0] * y * (1.0 - pair.jaw) + bone_rotation[1] * y * pair.jaw)
    height = wp.dot(particle_q[pair.upper] - particle_q[pair.lower], up)
    overlap = wp.max(pair.gap - height, 0.0) - wp.max(height - pair.most, 0.0)
    if overlap == 0.0:
        return
    if pair.upper_share > 0.0:
        wp.atomic_add(particle_move, pair.upper, up * (pair.upper_share * overlap))
        _count_move(particle_moves, pair.upper, touched, pass_counts)
    if pair.upper_share < 1.0:
        wp.atomic_add(particle_move, pair.lower, up * ((pair.upper_share - 1.0) * overlap))
        _count_move(particle_moves, pair.lower, touched, pass_counts)
    wp.atomic_add(pass_counts, 0, 1)


@wp.kernel
def forget_moved(moved: wp.array(dtype=int), moved_counts: wp.array(dtype=int), which: int, chunk: int,
                 particle_moved: wp.array(dtype=int)):
    """Before a pass's moves are applied: the particles the previous pass moved
    (moved[:moved_counts[which]]) are no longer flagged, and the other list is emptied for
    apply_guard to fill."""
    start = wp.tid() * chunk
    for e in range(start, wp.min(start + chunk, moved_counts[which])):
        particle_moved[moved[e]] = 0
    if wp.tid() == 0:
        moved_counts[1 - which] = 0


@wp.kernel
def apply_guard(particle_static: wp.array(dtype=ParticleStatic), particle_move: wp.array(dtype=wp.vec3),
                particle_moves: wp.array(dtype=float), particle_crease: wp.array(dtype=wp.vec3),
                bone_rotation: wp.array(dtype=wp.mat33),
                bone_translation: wp.array(dtype=wp.vec3),
                head_sdf: wp.array3d(dtype=float), head_sdf_origin: wp.vec3, head_sdf_spacing: float,
                jaw_sdf: wp.array3d(dtype=float), jaw_sdf_origin: wp.vec3, jaw_sdf_spacing: float,
                contact_depth: float, touched: wp.array(dtype=int), pass_counts: wp.array(dtype=int), chunk: int,
                which: int, particle_q: wp.array(dtype=wp.vec3), particle_qd: wp.array(dtype=wp.vec3),
                particle_moved: wp.array(dtype=int), moved: wp.array(dtype=int), moved_counts: wp.array(dtype=int)):
    """Each particle the pass moved (touched[:pass_counts[1]]), if movable, moves by the mean
    of its moves, and a move that reached a bone stops on it as a step does
    (fae.sim.collision); its move arrays are cleared for the next pass, and it is flagged in
    `particle_moved` and listed in moved[:moved_counts[1 - which]] for that pass to look
    next to."""
    start = wp.tid() * chunk
    R0 = bone_rotation[0]
    R1 = bone_rotation[1]
    t0 = bone_translation[0]
    t1 = bone_translation[1]
    for e in range(start, wp.min(start + chunk, pass_counts[1])):
        i = touched[e]
        m = particle_moves[i]
        ps = particle_static[i]
        if ps.inv_mass > 0.0:
            particle_moved[i] = 1
            moved[wp.atomic_add(moved_counts, 1 - which, 1)] = i
            x0 = particle_q[i]
            x = x0 + particle_move[i] / m
            # a crease move is inelastic: the velocity that pushed against it goes, else
            # the next step pushes the same way and the skin rocks at a held pose
            c = particle_crease[i]
            against = wp.dot(particle_qd[i], c)
            if against < 0.0:
                particle_qd[i] = particle_qd[i] - c * (against / wp.dot(c, c))
            if ps.collider != 0:
                v = particle_qd[i]
                rest = ps.rest
                target = (R0 * rest + t0) * (1.0 - ps.jaw) + (R1 * rest + t1) * ps.jaw
                x, v = skull_then_jaw_contact(x0, x, v, rest, target, ps.clearance, head_sdf, head_sdf_origin,
                                              head_sdf_spacing, R0, t0, jaw_sdf, jaw_sdf_origin, jaw_sdf_spacing,
                                              R1, t1, contact_depth)
                particle_qd[i] = v
            if ps.sphere[3] > 0.0 or ps.sphere_max > 0.0:
                v = particle_qd[i]
                x, v = sphere_contact(x, v, ps.sphere, ps.sphere_max, R0, t0)
                particle_qd[i] = v
            particle_q[i] = x
        particle_move[i] = wp.vec3(0.0, 0.0, 0.0)
        particle_moves[i] = 0.0
        particle_crease[i] = wp.vec3(0.0, 0.0, 0.0)
