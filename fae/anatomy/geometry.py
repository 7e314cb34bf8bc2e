"""Geometry helpers for building anatomical meshes from signed distances.

Signed distance functions take points `P (n, 3)` and return `(n,)` values, negative
inside. Shapes are combined with smooth minimum/maximum (polynomial blend of width `k`).
Meshes are `V (n, 3) float64, F (m, 3) int` with counter-clockwise faces seen from outside.
All functions are pure: inputs are never modified.
"""

from __future__ import annotations

import numpy as np

from fae.mesh import adjacency, boundary_edges, boundary_vertices, triangle_normals, vertex_normals
from fae.mesh import edges as mesh_edges


# ---------------------------------------------------------------------------------------
# signed distance primitives (approximate where exact is costly; all 1-Lipschitz-ish)

def sdf_ellipsoid(P: np.ndarray, center, radii) -> np.ndarray:
    """(n,) approximate signed distance to an axis-aligned ellipsoid (bound-corrected)."""
    q = (P - np.asarray(center, dtype=np.float64)) / np.asarray(radii, dtype=np.float64)
    k0 = np.sqrt(np.einsum("ij,ij->i", q, q))
    q2 = q / np.asarray(radii, dtype=np.float64)
    k1 = np.sqrt(np.einsum("ij,ij->i", q2, q2))
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def sdf_sphere(P: np.ndarray, center, radius: float) -> np.ndarray:
    """(n,) signed distance to a sphere."""
    return np.linalg.norm(P - np.asarray(center, dtype=np.float64), axis=1) - radius


def segment_parameter(P: np.ndarray, a, b) -> np.ndarray:
    """(n,) parameter t in [0, 1] of the point of segment a-b closest to each point."""
    a = np.asarray(a, dtype=np.float64)
    ab = np.asarray(b, dtype=np.float64) - a
    return np.clip((P - a) @ ab / float(ab @ ab), 0.0, 1.0)


def sdf_capsule(P: np.ndarray, a, b, ra: float, rb: float | None = None) -> np.ndarray:
    """(n,) signed distance to a capsule from a to b, radius ra at a and rb at b."""
    rb = ra if rb is None else rb
    t = segment_parameter(P, a, b)
    a = np.asarray(a, dtype=np.float64)
    c = a + t[:, None] * (np.asarray(b, dtype=np.float64) - a)
    return np.linalg.norm(P - c, axis=1) - (ra + (rb - ra) * t)


def sdf_polyline(P: np.ndarray, points, radii) -> np.ndarray:
    """(n,) union of tapered capsules along a polyline `points (k, 3)` with `radii (k,)`."""
    points = np.asarray(points, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    d = np.full(P.shape[0], np.inf)
    for i in range(len(points) - 1):
        d = np.minimum(d, sdf_capsule(P, points[i], points[i + 1], radii[i], radii[i + 1]))
    return d


def sdf_round_box(P: np.ndarray, center, half_size, radius: float) -> np.ndarray:
    """(n,) signed distance to an axis-aligned box with rounded edges."""
    q = np.abs(P - np.asarray(center, dtype=np.float64)) - (np.asarray(half_size, dtype=np.float64) - radius)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside - radius


def sdf_column(P: np.ndarray, center_xz, half_xz, corner: float, bottom: float, top: float,
               edge: float) -> np.ndarray:
    """(n,) signed distance to an upright column: a rectangle in xz (centre (2,), half sizes
    (2,), corners rounded by `corner`) swept from height `bottom` to `top`, its flat ends'
    rims rounded by `edge` (a rounded box would round its ends by `corner` too)."""
    q = np.abs(P[:, [0, 2]] - np.asarray(center_xz, dtype=np.float64)) - (np.asarray(half_xz, dtype=np.float64) - corner)
    across = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0) - corner
    along = np.abs(P[:, 1] - 0.5 * (top + bottom)) - 0.5 * (top - bottom)
    w = np.stack([across + edge, along + edge], axis=1)
    return np.linalg.norm(np.maximum(w, 0.0), axis=1) + np.minimum(w.max(axis=1), 0.0) - edge


def smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of two distance fields, blend width k (same unit)."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def smooth_subtract(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Shape a with shape b carved out, blend width k."""
    return -smooth_union(-a, b, k)


def smooth_intersect(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth intersection of two shapes, blend width k."""
    return -smooth_union(-a, -b, k)


# ---------------------------------------------------------------------------------------
# meshing

def grid_points(lo, hi, step: float) -> tuple[np.ndarray, tuple[int, int, int], np.ndarray]:
    """Regular grid from `lo` (3,) with spacing `step` covering `hi`.

    Returns (P (nx*ny*nz, 3) in C order, shape (nx, ny, nz), origin (3,)).
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    n = np.ceil((hi - lo) / step).astype(int) + 1
    axes = [lo[i] + step * np.arange(n[i]) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    return P, (int(n[0]), int(n[1]), int(n[2])), lo


def marching_cubes(values: np.ndarray, origin, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of a sampled signed distance (negative inside) as (V, F), faces outward."""
    from skimage.measure import marching_cubes as _mc

    verts, faces, _normals, _vals = _mc(values, level=0.0, spacing=(step, step, step),
                                        gradient_direction="ascent", allow_degenerate=False)
    V = verts.astype(np.float64) + np.asarray(origin, dtype=np.float64)
    F = faces.astype(np.int64)
    return V, F


def sample_sdf(sdf, lo, step: float, shape, coarse: int = 4, band: float | None = None) -> np.ndarray:
    """Values of `sdf` on the grid lo + step * (i, j, k), `shape` (nx, ny, nz).

    The field is first sampled every `coarse` steps and interpolated; it is evaluated
    exactly wherever the interpolated value lies within `band` of zero (default: two
    coarse cells), which is everywhere the zero set can be for a field with slope <= 1.
    """
    from scipy.ndimage import map_coordinates

    lo = np.asarray(lo, dtype=np.float64)
    shape = tuple(int(n) for n in shape)
    nc = [(n - 1) // coarse + 2 for n in shape]
    axes = [lo[i] + step * coarse * np.arange(nc[i]) for i in range(3)]
    Pc = np.stack([a.ravel() for a in np.meshgrid(*axes, indexing="ij")], axis=1)
    coarse_values = sdf(Pc).reshape(nc)
    idx = np.meshgrid(*[np.arange(n, dtype=np.float64) / coarse for n in shape], indexing="ij")
    values = map_coordinates(coarse_values, idx, order=1, mode="nearest")
    band = 2.0 * coarse * step if band is None else band
    near = np.abs(values) < band
    ijk = np.argwhere(near)
    values[near] = sdf(lo + step * ijk.astype(np.float64))
    return values


def mesh_from_sdf(sdf, lo, hi, step: float, pad: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Mesh (V, F) of the shape `sdf(P) < 0` inside the box lo..hi.

    With `pad` the box grows by two steps on every side, so the mesh is closed; without
    it, the surface ends in open borders on the box faces it crosses.
    """
    lo = np.asarray(lo, dtype=np.float64) - (2 * step if pad else 0.0)
    hi = np.asarray(hi, dtype=np.float64) + (2 * step if pad else 0.0)
    shape = np.ceil((hi - lo) / step).astype(int) + 1
    values = sample_sdf(sdf, lo, step, shape)
    V, F = marching_cubes(values, lo, step)
    return orient_outward(*remove_unreferenced(V, F))


def remove_unreferenced(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V', F') without vertices no face uses, order kept."""
    used = np.zeros(len(V), dtype=bool)
    used[F.ravel()] = True
    remap = np.cumsum(used) - 1
    return V[used], remap[F]


def signed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Signed volume enclosed by a closed mesh (positive when faces point outward)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def orient_outward(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flip all faces if the mesh's signed volume is negative."""
    if signed_volume(V, F) < 0:
        F = F[:, ::-1]
    return V, np.ascontiguousarray(F)


def largest_component(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The connected component (by shared vertices) with the most faces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(V)
    rows = np.concatenate([F[:, 0], F[:, 1], F[:, 2]])
    cols = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _count, labels = connected_components(graph, directed=False)
    face_label = labels[F[:, 0]]
    keep = face_label == np.bincount(face_label).argmax()
    return remove_unreferenced(V, F[keep])


def decimate(V: np.ndarray, F: np.ndarray, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric-error decimation to about `target_faces` faces (open borders may slide)."""
    import pyfqmr

    simplifier = pyfqmr.Simplify()
    simplifier.setMesh(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int32))
    simplifier.simplify_mesh(target_count=int(target_faces), aggressiveness=7, preserve_border=False,
                             verbose=False, max_iterations=200)
    V2, F2, _ = simplifier.getMesh()
    return remove_unreferenced(np.asarray(V2, dtype=np.float64), np.asarray(F2, dtype=np.int64))


def mirror_half(V: np.ndarray, F: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mirror a half mesh lying in x >= 0 whose open border lies on x = 0.

    Border vertices are snapped to x = 0 exactly and shared by both halves.
    Returns (V2 (n2, 3), F2 (m2, 3), mirror (n2,) int: index of each vertex's x -> -x partner).
    """
    V = V.copy()
    border = np.zeros(len(V), dtype=bool)
    border[boundary_edges(F).ravel()] = True
    if np.any(np.abs(V[border, 0]) > tol):
        raise ValueError(f"mirror_half: open border leaves the plane x = 0 by {np.abs(V[border, 0]).max():g}")
    V[border, 0] = 0.0
    # midline vertices first, then the x > 0 side, then its mirror image
    order = np.concatenate([np.flatnonzero(border), np.flatnonzero(~border)])
    remap = np.empty(len(V), dtype=np.int64)
    remap[order] = np.arange(len(V))
    V = V[order]
    F = remap[F]
    n_mid = int(border.sum())
    n = len(V)
    side = np.arange(n_mid, n)
    Vm = V[side] * np.array([-1.0, 1.0, 1.0])
    index_m = np.arange(n, dtype=np.int64)
    index_m[side] = n + np.arange(len(side))
    Fm = index_m[F][:, ::-1]
    V2 = np.concatenate([V, Vm])
    F2 = np.concatenate([F, Fm])
    # a side vertex i pairs with n + (i - n_mid); midline vertices pair with themselves
    mirror = np.empty(len(V2), dtype=np.int64)
    mirror[:n_mid] = np.arange(n_mid)
    mirror[n_mid:n] = n + np.arange(len(side))
    mirror[n:] = side
    return V2, F2, mirror


def closest_surface_points(V: np.ndarray, F: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each query point (k, 3): (closest point (k, 3), triangle (k,), barycentric (k, 3))."""
    import trimesh

    mesh = trimesh.Trimesh(V, F, process=False)
    closest, _dist, tri = trimesh.proximity.closest_point(mesh, np.asarray(points, dtype=np.float64))
    bary = trimesh.triangles.points_to_barycentric(V[F[tri]], closest)
    return closest, tri.astype(np.int64), bary


def ray_hits(V: np.ndarray, F: np.ndarray, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(k, 3) first hit of each ray on the mesh (nan where a ray misses)."""
    import trimesh

    mesh = trimesh.Trimesh(V, F, process=False)
    locs, ray_idx, _tri = mesh.ray.intersects_location(origins, directions, multiple_hits=True)
    out = np.full((len(origins), 3), np.nan)
    best = np.full(len(origins), np.inf)
    for loc, r in zip(locs, ray_idx):
        d = float(np.dot(loc - origins[r], directions[r]))
        if 0 <= d < best[r]:
            best[r] = d
            out[r] = loc
    return out


# ---------------------------------------------------------------------------------------
# mesh quality: quadric decimation leaves long slivers where a surface is flat along one
# direction (a neck's straight sides); they crease when fitted or simulated

def _edge_faces(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (e, 2) of F (m, 3) and their faces (e, 2) (-1: border)."""
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    face = np.tile(np.arange(len(F)), 3)
    key = np.sort(directed, axis=1)
    E, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    faces = np.full((len(E), 2), -1, dtype=np.int64)
    first = np.ones(len(order), dtype=bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    faces[inverse[order][first], 0] = face[order][first]
    faces[inverse[order][~first], 1] = face[order][~first]
    return E, faces


def _independent(edge_faces: np.ndarray, candidates: np.ndarray, face_count: int) -> np.ndarray:
    """Candidates (in order) whose faces no earlier chosen candidate touches."""
    taken = np.zeros(face_count + 1, dtype=bool)  # the last slot stands for "no face"
    chosen = []
    for e in candidates:
        f = edge_faces[e]
        if taken[f[f >= 0]].any():
            continue
        taken[f[f >= 0]] = True
        chosen.append(e)
    return np.array(chosen, dtype=np.int64)


SPLIT_ROUNDS = 200  # of split_long_edges (the generic head's neck takes 9, its ramus 6)


def split_long_edges(V: np.ndarray, F: np.ndarray, max_edge: float, allowed: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V', F', allowed') with every edge between allowed faces (m,) bool longer than
    `max_edge` split at its midpoint, longest first; each face beside a split edge becomes
    two. New vertices are appended to V (n, 3), new faces to F (m, 3), orientation kept.
    Raises RuntimeError after SPLIT_ROUNDS rounds (an allowed region hemmed in by faces it
    may not split can grow a long edge back with every split)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    allowed = np.asarray(allowed, dtype=bool)
    for _ in range(SPLIT_ROUNDS):
        E, EF = _edge_faces(F)
        length = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
        in_zone = allowed[EF[:, 0]] & np.where(EF[:, 1] >= 0, allowed[np.maximum(EF[:, 1], 0)], True)
        long = np.flatnonzero(in_zone & (length > max_edge))
        if len(long) == 0:
            return V, F, allowed
        chosen = _independent(EF, long[np.argsort(-length[long])], len(F))
        mid = len(V) + np.arange(len(chosen))
        V = np.vstack([V, 0.5 * (V[E[chosen, 0]] + V[E[chosen, 1]])])
        new_faces, new_allowed = [], []
        F = F.copy()
        for e, m in zip(chosen, mid):
            a, b = E[e]
            for f in EF[e][EF[e] >= 0]:
                tri = F[f]
                k = next(k for k in range(3) if {tri[k], tri[(k + 1) % 3]} == {a, b})
                u, w, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
                F[f] = (u, m, c)
                new_faces.append((m, w, c))
                new_allowed.append(allowed[f])
        F = np.vstack([F, np.array(new_faces, dtype=np.int64).reshape(-1, 3)])
        allowed = np.concatenate([allowed, np.array(new_allowed, dtype=bool)])
    raise RuntimeError(f"split_long_edges: edges over {max_edge} still grow back after {SPLIT_ROUNDS} rounds of "
                       "splits; allow the faces around the long ones too")


def _corner_angle(V: np.ndarray, apex: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    u, w = V[a] - V[apex], V[b] - V[apex]
    c = np.sum(u * w, axis=1) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
    return np.arccos(np.clip(c, -1.0, 1.0))


def flip_to_delaunay(V: np.ndarray, F: np.ndarray, allowed: np.ndarray, max_dihedral: float = 35.0,
                     rounds: int = 30) -> np.ndarray:
    """F' (m, 3): interior edges between two allowed faces flipped while the angles facing
    them sum to more than 180 degrees (the Delaunay condition), where the two faces are
    within `max_dihedral` degrees of flat (a flip there does not change the shape)."""
    F = np.asarray(F, dtype=np.int64).copy()
    allowed = np.asarray(allowed, dtype=bool)
    cos_max = np.cos(np.radians(max_dihedral))
    for _ in range(rounds):
        E, EF = _edge_faces(F)
        inner = (EF[:, 1] >= 0) & allowed[EF[:, 0]] & allowed[np.maximum(EF[:, 1], 0)]
        idx = np.flatnonzero(inner)
        f0, f1 = F[EF[idx, 0]], F[EF[idx, 1]]
        a, b = E[idx, 0], E[idx, 1]
        c = f0.sum(axis=1) - a - b  # the corner of each face opposite the edge
        d = f1.sum(axis=1) - a - b
        want = _corner_angle(V, c, a, b) + _corner_angle(V, d, a, b) > np.pi + 1e-6
        n0 = np.cross(V[f0[:, 1]] - V[f0[:, 0]], V[f0[:, 2]] - V[f0[:, 0]])
        n1 = np.cross(V[f1[:, 1]] - V[f1[:, 0]], V[f1[:, 2]] - V[f1[:, 0]])
        flat = np.sum(n0 * n1, axis=1) >= cos_max * np.linalg.norm(n0, axis=1) * np.linalg.norm(n1, axis=1)
        existing = set(map(tuple, E))
        candidates = [i for i in np.flatnonzero(want & flat)
                      if (min(c[i], d[i]), max(c[i], d[i])) not in existing]
        chosen = _independent(EF[idx], np.array(candidates, dtype=np.int64), len(F))
        if len(chosen) == 0:
            break
        for i in chosen:
            g0, g1 = EF[idx[i]]
            tri = F[g0]
            k = next(k for k in range(3) if {tri[k], tri[(k + 1) % 3]} == {a[i], b[i]})
            u, w = tri[k], tri[(k + 1) % 3]  # face g0 runs u -> w; face g1 runs w -> u
            F[g0] = (u, d[i], c[i])
            F[g1] = (w, c[i], d[i])
    return F


def _segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """(k,) distances between the segments p0-p1 and q0-q1 (each (k, 3), of non-zero
    length): the closest parameters on both lines, clamped to the segments (Ericson,
    Real-Time Collision Detection, 5.1.9)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e = np.sum(d1 * d1, axis=1), np.sum(d2 * d2, axis=1)
    b, c, f = np.sum(d1 * d2, axis=1), np.sum(d1 * r, axis=1), np.sum(d2 * r, axis=1)
    denom = a * e - b * b
    parallel = denom <= 1e-12 * a * e
    s = np.where(parallel, 0.0, np.clip((b * f - c * e) / np.where(parallel, 1.0, denom), 0.0, 1.0))
    t = (b * s + f) / e
    s = np.where(t < 0.0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p0 + d1 * s[:, None] - q0 - d2 * t[:, None], axis=1)


def _corner_angles(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 3) radians: each face's corner angles, in the order of its corners."""
    return np.stack([_corner_angle(V, F[:, k], F[:, (k + 1) % 3], F[:, (k + 2) % 3]) for k in range(3)], axis=1)


def flip_caps(V: np.ndarray, F: np.ndarray, allowed: np.ndarray, cap_angle: float = 130.0,
              max_change: float = 0.5, min_valence: int = 5, severe_angle: float = 150.0,
              rounds: int = 10) -> np.ndarray:
    """F' (m, 3): caps among the allowed faces (m,) bool of mesh V (n, 3), F (m, 3) flipped
    away where that is safe: the long edge facing a face's widest corner (> cap_angle
    degrees) is flipped where the face across it is allowed too and the flip
    - narrows: the widest corner of the two new faces is smaller than of the two old ones;
    - keeps the shape: the new edge passes within max_change (V's unit) of the old one,
      however curved the skin (unlike flip_to_delaunay's limit on the faces' dihedral: a
      lid's margin is curved, and its caps are exactly where the two faces are not flat);
    - keeps the quad convex: at both ends of the old edge, the two faces' corners sum to
      less than 180 degrees;
    - leaves both ends of the old edge with at least min_valence edges, unless the corner
      is wider than severe_angle (a vertex of three or four edges makes a spike), counting
      the flips made before it in the same round.
    A cap that no flip may remove stays. No vertex moves. Only the faces around the allowed
    faces' vertices take part (every edge at those vertices, so their valences and the edges
    that exist are the whole mesh's): an adapted head's upper lids flip in 0.02-0.03 s
    instead of 0.3-0.5 s over its whole skin."""
    F = np.asarray(F, dtype=np.int64).copy()
    V = np.asarray(V, dtype=np.float64)
    allowed = np.asarray(allowed, dtype=bool)
    around = np.flatnonzero(np.isin(F, F[allowed]).any(axis=1))
    if len(around) < len(F):
        F[around] = flip_caps(V, F[around], allowed[around], cap_angle, max_change, min_valence, severe_angle, rounds)
        return F
    cap = np.radians(cap_angle)
    severe = np.radians(severe_angle)
    for _ in range(rounds):
        E, EF = _edge_faces(F)
        index = {(int(a), int(b)): i for i, (a, b) in enumerate(E)}
        valence = np.bincount(E.ravel(), minlength=len(V))
        corners = _corner_angles(V, F)
        widest = corners.max(axis=1)
        faces = np.flatnonzero(allowed & (widest > cap))
        faces = faces[np.argsort(-widest[faces], kind="stable")]
        candidates = []
        spiky = {}  # candidate edge -> whether its ends must keep min_valence
        for f in faces:
            k = int(np.argmax(corners[f]))
            c, a, b = F[f, k], F[f, (k + 1) % 3], F[f, (k + 2) % 3]
            e = index[(min(a, b), max(a, b))]
            g = EF[e, 1] if EF[e, 0] == f else EF[e, 0]
            if g < 0 or not allowed[g]:
                continue
            d = int(F[g].sum() - a - b)
            if (min(c, d), max(c, d)) in index:
                continue
            if _corner_angles(V, np.array([[c, a, d], [c, d, b]])).max() >= max(widest[f], widest[g]):
                continue
            # the quad's angles at a and at b: each the two old faces' corners there
            quad = _corner_angle(V, np.array([a, a, b, b]), np.array([c, d, c, d]), np.array([b, b, a, a]))
            if quad[0] + quad[1] >= np.pi or quad[2] + quad[3] >= np.pi:
                continue
            if not _segment_distance(V[[a]], V[[b]], V[[c]], V[[d]])[0] <= max_change:  # (NaN: degenerate)
                continue
            candidates.append(e)
            spiky[e] = widest[f] <= severe
        chosen = _independent(EF, np.array(candidates, dtype=np.int64), len(F))
        made = set()  # edges the round's flips made
        flipped = 0
        for e in chosen:
            g0, g1 = EF[e]
            a, b = E[e]
            tri = F[g0]
            k = next(k for k in range(3) if {tri[k], tri[(k + 1) % 3]} == {a, b})
            u, w = tri[k], tri[(k + 1) % 3]  # face g0 runs u -> w; face g1 runs w -> u
            c = int(tri.sum() - u - w)
            d = int(F[g1].sum() - u - w)
            if (min(c, d), max(c, d)) in made or (spiky[e] and min(valence[a], valence[b]) - 1 < min_valence):
                continue
            F[g0] = (u, d, c)
            F[g1] = (w, c, d)
            made.add((min(c, d), max(c, d)))
            valence[[a, b]] -= 1
            valence[[c, d]] += 1
            flipped += 1
        if flipped == 0:
            break
    return F


def refine_long_triangles(V: np.ndarray, F: np.ndarray, max_edge: float, allowed: np.ndarray,
                          cycles: int = 3, relax: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(V', F'): the allowed faces (m,) bool of mesh V (n, 3), F (m, 3) without edges longer
    than `max_edge`: long edges split (split_long_edges), then `cycles` times Delaunay
    flips and `relax` rounds of tangential smoothing of the vertices inside the allowed
    faces, each put back onto the input surface. Vertices keep their indices (new ones are
    appended); vertices on the open border (a half mesh's plane x = 0) do not move."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    V2, F2, allowed2 = split_long_edges(V, F, max_edge, allowed)
    if len(V2) == len(V):
        return V2, F2
    free = np.ones(len(V2), dtype=bool)
    free[F2[~allowed2].ravel()] = False
    free[boundary_edges(F2).ravel()] = False
    free = np.flatnonzero(free)
    for _ in range(cycles):
        F2 = flip_to_delaunay(V2, F2, allowed2)
        A = adjacency(F2, len(V2))
        degree = np.asarray(A.sum(axis=1)).ravel()
        for _ in range(relax):
            step = (A @ V2)[free] / degree[free, None] - V2[free]
            N = vertex_normals(V2, F2)[free]
            step -= np.sum(step * N, axis=1, keepdims=True) * N
            V2[free] = closest_surface_points(V, F, V2[free] + step)[0]
    # relaxing can stretch an edge a little past the limit again: split, onto the surface
    n2 = len(V2)
    V2, F2, _ = split_long_edges(V2, F2, max_edge, allowed2)
    if len(V2) > n2:
        V2[n2:] = closest_surface_points(V, F, V2[n2:])[0]
    return V2, F2


def _round_state(V: np.ndarray, F: np.ndarray) -> tuple:
    """A round of vertex merges starts: (adjacency (n, n) csr, the faces at each vertex,
    locked (n,) bool, dead (m,) bool), the last two all False."""
    vertex_faces = [[] for _ in range(len(V))]
    for i, tri in enumerate(F):
        for v in tri:
            vertex_faces[v].append(i)
    return (adjacency(F, len(V)).tocsr(), vertex_faces, np.zeros(len(V), dtype=bool),
            np.zeros(len(F), dtype=bool))


def _apply_merge(F: np.ndarray, A, locked: np.ndarray, dead: np.ndarray, c: int, merge: tuple) -> None:
    """Merge vertex c as `merge` (from _vertex_merge) says, in place: its faces move to the
    kept vertex, the two on their edge die, and both vertices' rings lock for the round
    (a merge checked against faces a neighbour's merge has changed could fold them)."""
    t, both, around, new, _ = merge
    F[around] = new
    dead[both] = True
    locked[A[c].indices] = True
    locked[A[t].indices] = True
    locked[[c, t]] = True


def _vertex_merge(V, F, A, vertex_faces, dead, locked, border, c: int, t: int, max_corner: float):
    """(t, the two faces on edge c-t, the other faces around c, those faces with c moved
    to t, the least cosine of their turns) when vertex c may be merged into its neighbour
    t: neither locked this round, c not on the open border, the mesh kept manifold (the two
    share exactly the two neighbours across their edge), no face around c turned by more
    than 30 degrees and no corner of `max_corner` radians or more opened (a cap's own
    angle); else None."""
    if locked[c] or locked[t] or border[c]:
        return None
    shared = np.intersect1d(A[c].indices, A[t].indices)
    both = [g for g in vertex_faces[c] if t in F[g] and not dead[g]]
    if len(both) != 2 or len(shared) != 2:
        return None
    around = [g for g in vertex_faces[c] if g not in both and not dead[g]]
    if not around:
        return None
    old = F[around]
    new = np.where(old == c, t, old)
    n_old, n_new = triangle_normals(V, old), triangle_normals(V, new)
    norm = np.linalg.norm(n_old, axis=1) * np.linalg.norm(n_new, axis=1)
    cos = np.sum(n_old * n_new, axis=1) / np.maximum(norm, 1e-300)
    if not np.all(cos > np.cos(np.radians(30.0))) or _corner_angles(V, new).max() >= max_corner:
        return None
    return t, both, around, new, float(cos.min())


def collapse_caps(V: np.ndarray, F: np.ndarray, allowed: np.ndarray, cap_angle: float = 150.0,
                  rounds: int = 5, far_end: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(V', F'): caps among the allowed faces (m,) bool of mesh V (n, 3), F (m, 3) removed by
    moving each cap's apex (its widest corner, over cap_angle degrees) onto the nearer end of
    its long edge and merging the two. Where a sharp edge runs through three vertices almost
    in a line (a lip's inner rim), a cap lies along it: its normal is the average of the
    two sides', and an apex moved a fraction of a millimetre turns it over. Flipping its long
    edge instead (flip_caps) joins the apex to the far side and the rim turned jagged as it
    moved; merged, the rim keeps its run of edges with one vertex less. A merge is made only
    where the mesh stays manifold (the two vertices share exactly the two neighbours across
    their edge), no face around the apex turns by more than 30 degrees or gets a corner wider
    than the cap's, and the apex is not on the open border (a half mesh's plane x = 0: merged
    along an edge inside, the border would pass twice through the kept vertex). far_end:
    None, or (m,) bool: caps whose apex goes to the farther end where the nearer one fails
    those checks (a lower lid's outer corner, where the near end would turn the face beside
    it over; not at the mouth corners, where the longer edges it leaves stretched 2.8x as
    a viseme narrowed the mouth). Unused vertices are dropped; V' keeps V's order otherwise."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).copy()
    allowed = np.asarray(allowed, dtype=bool).copy()
    far_end = np.zeros(len(F), dtype=bool) if far_end is None else np.asarray(far_end, dtype=bool).copy()
    cap = np.radians(cap_angle)
    for _ in range(rounds):
        border = boundary_vertices(F, len(V))
        corners = _corner_angles(V, F)
        widest = corners.max(axis=1)
        faces = np.flatnonzero(allowed & (widest > cap))
        faces = faces[np.argsort(-widest[faces], kind="stable")]
        if len(faces) == 0:
            break
        A, vertex_faces, locked, dead = _round_state(V, F)
        merged = 0
        for f in faces:
            if dead[f]:
                continue
            k = int(np.argmax(corners[f]))
            c, a, b = (int(x) for x in (F[f, k], F[f, (k + 1) % 3], F[f, (k + 2) % 3]))
            # the nearer end first (the apex moves least), then (far_end) the farther one;
            # a nearer end locked this round is tried again in the next
            ends = sorted((a, b), key=lambda v: np.linalg.norm(V[v] - V[c]))[:2 if far_end[f] else 1]
            if locked[ends[0]]:
                continue
            merge = next((m for t in ends if (m := _vertex_merge(V, F, A, vertex_faces, dead, locked, border, c, t,
                                                                 widest[f])) is not None), None)
            if merge is None:
                continue
            _apply_merge(F, A, locked, dead, c, merge)
            merged += 1
        if merged == 0:
            break
        F, allowed, far_end = F[~dead], allowed[~dead], far_end[~dead]
    return remove_unreferenced(V, F)


def collapse_short_edges(V: np.ndarray, F: np.ndarray, allowed: np.ndarray, min_length: float,
                         max_angle: float = 150.0, rounds: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(V', F'): edges shorter than min_length of the allowed faces (m,) bool of mesh V (n,
    3), F (m, 3) merged away, shortest first: one end moved onto the other (the end whose
    move turns the faces around it least), where the mesh stays manifold, no face around
    the moved end turns by more than 30 degrees nor gets a corner of max_angle degrees or
    more, and the moved end is not on the open border. A short edge among long ones leaves
    needles beside it (a mouth corner's rim: 0.5 mm among 3-5 mm edges, corners of 6
    degrees) whose normals turn over at the slightest motion. Unused vertices are dropped;
    V' keeps V's order otherwise."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).copy()
    allowed = np.asarray(allowed, dtype=bool).copy()
    limit = np.radians(max_angle)
    for _ in range(rounds):
        border = boundary_vertices(F, len(V))
        E = mesh_edges(F[allowed])
        length = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
        short = np.argsort(length, kind="stable")
        short = short[length[short] < min_length]
        if len(short) == 0:
            break
        A, vertex_faces, locked, dead = _round_state(V, F)
        merged = 0
        for u, v in E[short]:
            best = None
            for c, t in ((int(u), int(v)), (int(v), int(u))):
                m = _vertex_merge(V, F, A, vertex_faces, dead, locked, border, c, t, limit)
                if m is not None and (best is None or m[4] > best[1][4]):
                    best = (c, m)  # the end whose faces turn least
            if best is None:
                continue
            _apply_merge(F, A, locked, dead, *best)
            merged += 1
        if merged == 0:
            break
        F, allowed = F[~dead], allowed[~dead]
    return remove_unreferenced(V, F)
