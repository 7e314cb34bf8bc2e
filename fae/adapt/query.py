"""Ray casting and closest-point queries against triangle meshes (Warp BVH, CPU by default).

trimesh's pure-Python ray intersector costs about 12 ms per ray on a 100k-triangle scan
here (no Embree), so the queries run as Warp kernels over a `wp.Mesh` BVH instead.
Points go in and come out as float64 numpy arrays; Warp works in float32 internally
(about 1e-8 m at head scale).
"""

from __future__ import annotations

import numpy as np
from fae.warp_setup import launch_split, wp

# nothing here is differentiated: no adjoint code to compile
wp.set_module_options({"enable_backward": False})

_initialized = False


def init_warp() -> None:
    """Initialize Warp once (configured by fae.warp_setup)."""
    global _initialized
    if not _initialized:
        wp.init()
        _initialized = True


@wp.kernel
def _ray_kernel(mesh: wp.uint64, origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                max_t: float, first: int, hit_t: wp.array(dtype=float), hit_face: wp.array(dtype=int),
                hit_bary: wp.array(dtype=wp.vec3)):
    i = wp.tid() + first
    q = wp.mesh_query_ray(mesh, origins[i], directions[i], max_t)
    if q.result:
        hit_t[i] = q.t
        hit_face[i] = q.face
        hit_bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
    else:
        hit_face[i] = -1


@wp.kernel
def _closest_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float, first: int,
                    out_face: wp.array(dtype=int), out_bary: wp.array(dtype=wp.vec3)):
    i = wp.tid() + first
    q = wp.mesh_query_point_no_sign(mesh, points[i], max_dist)
    if q.result:
        out_face[i] = q.face
        out_bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
    else:
        out_face[i] = -1


@wp.kernel
def _signed_distance_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float, first: int,
                            out_distance: wp.array(dtype=float)):
    # distance to the closest surface point, negative inside; max_dist + 1 where none is that close
    i = wp.tid() + first
    q = wp.mesh_query_point_sign_normal(mesh, points[i], max_dist)
    if q.result:
        out_distance[i] = q.sign * wp.length(points[i] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
    else:
        out_distance[i] = max_dist + 1.0


@wp.kernel
def _segment_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                    ends: wp.array(dtype=wp.int32), same: float, first: int, out_face: wp.array(dtype=int)):
    # segment e joins mesh vertices ends[2e], ends[2e+1]; the first triangle it passes through,
    # among those overlapping its bounding box that share no corner with it, or -1
    e = wp.tid() + first
    ia = ends[2 * e]
    ib = ends[2 * e + 1]
    a = points[ia]
    b = points[ib]
    d = b - a
    tol = same * wp.length(d)
    out_face[e] = -1
    if wp.length(d) <= 1.0e-9:
        return
    q = wp.mesh_query_aabb(mesh, wp.min(a, b), wp.max(a, b))
    for f in q:
        i0 = indices[3 * f]
        i1 = indices[3 * f + 1]
        i2 = indices[3 * f + 2]
        if i0 == ia or i0 == ib or i1 == ia or i1 == ib or i2 == ia or i2 == ib:
            continue
        p0 = points[i0]
        p1 = points[i1]
        p2 = points[i2]
        near_a = wp.min(wp.min(wp.length(p0 - a), wp.length(p1 - a)), wp.length(p2 - a))
        near_b = wp.min(wp.min(wp.length(p0 - b), wp.length(p1 - b)), wp.length(p2 - b))
        if near_a <= tol or near_b <= tol:  # a corner at an end's position (duplicated vertex)
            continue
        e1 = p1 - p0
        e2 = p2 - p0
        h = wp.cross(d, e2)
        det = wp.dot(e1, h)
        if wp.abs(det) < 1.0e-30:  # segment parallel to the triangle's plane
            continue
        s = a - p0
        u = wp.dot(s, h) / det
        if u < 0.0 or u > 1.0:
            continue
        c = wp.cross(s, e1)
        v = wp.dot(d, c) / det
        if v < 0.0 or u + v > 1.0:
            continue
        t = wp.dot(e2, c) / det
        if t > same and t < 1.0 - same:
            out_face[e] = f
            return


@wp.func
def _faces_share_a_vertex(indices: wp.array(dtype=wp.int32), f: int, g: int) -> bool:
    for a in range(3):
        for b in range(3):
            if indices[3 * f + a] == indices[3 * g + b]:
                return True
    return False


@wp.kernel
def _overlap_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                    pad: float, offsets: wp.array(dtype=int), fill: int, first: int,
                    out_count: wp.array(dtype=int), out_pairs: wp.array(dtype=int)):
    # face i against every later face g whose bounding box overlaps its own (grown by pad) and
    # which shares no corner with it: counted (fill 0) or written from offsets[i] on (fill 1)
    i = wp.tid() + first
    p0 = points[indices[3 * i]]
    p1 = points[indices[3 * i + 1]]
    p2 = points[indices[3 * i + 2]]
    grow = wp.vec3(pad, pad, pad)
    q = wp.mesh_query_aabb(mesh, wp.min(wp.min(p0, p1), p2) - grow, wp.max(wp.max(p0, p1), p2) + grow)
    k = int(0)
    if fill == 1:
        k = offsets[i]
    c = int(0)
    for g in q:
        if g > i and not _faces_share_a_vertex(indices, i, g):
            if fill == 1:
                out_pairs[2 * k] = i
                out_pairs[2 * k + 1] = g
                k += 1
            c += 1
    if fill == 0:
        out_count[i] = c


class MeshQuery:
    """A BVH over one triangle mesh: V (n, 3) float64, F (m, 3) int, any consistent unit."""

    def __init__(self, V: np.ndarray, F: np.ndarray):
        init_warp()
        self.V = np.asarray(V, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int32)
        if self.F.size == 0 or len(self.V) == 0:  # Warp's BVH of nothing crashed the process when queried
            raise ValueError("MeshQuery: a mesh without triangles has no surface to query")
        # Warp works in float32: about the mesh's own middle, not the file's origin (a survey's
        # scan 4,000 km from it had 0.25 m steps and its face was "8 % of the head" off it)
        self._origin = self.V.mean(axis=0)
        self._points = wp.array(self._local(self.V), dtype=wp.vec3, device="cpu")
        self._indices = wp.array(self.F.reshape(-1), dtype=wp.int32, device="cpu")
        self._mesh = wp.Mesh(points=self._points, indices=self._indices)

    def move(self, V: np.ndarray) -> None:
        """New positions V (n, 3) for the same vertices and faces: the BVH is refitted (a few
        ms), not rebuilt."""
        self.V = np.asarray(V, dtype=np.float64)
        self._points.numpy()[:] = self._local(self.V)
        self._mesh.refit()

    def _local(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) float32: points X about the mesh's middle, where Warp's float32 holds them."""
        return (np.asarray(X, dtype=np.float64) - self._origin).astype(np.float32)

    def _points_at(self, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """(k, 3) float64: the points of faces `face` (k,) at barycentric `bary` (k, 3), from the
        third corner along the edges: Warp's float32 weights times coordinates far from the
        origin (a survey's scan 1e5 units out) were off by a weight's rounding times that distance
        (0.5 mm on a bust's face, which was refused as fitted 1 % of its size off)."""
        corner = self.V[self.F[face]]
        return (corner[:, 2] + bary[:, :1] * (corner[:, 0] - corner[:, 2])
                + bary[:, 1:2] * (corner[:, 1] - corner[:, 2]))

    def ray_hits(self, origins: np.ndarray, directions: np.ndarray, max_t: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """First hits of rays along `directions` (n, 3, unit) from `origins` (n, 3).

        Returns hit (n,) bool, t (n,) distance along the ray, face (n,) int (-1: none),
        bary (n, 3) barycentric coordinates of the hit in its face.
        """
        n = len(origins)
        if n == 0:
            return np.zeros(0, bool), np.zeros(0), np.zeros(0, int), np.zeros((0, 3))
        o = wp.array(self._local(origins), dtype=wp.vec3, device="cpu")
        d = wp.array(np.asarray(directions, np.float32), dtype=wp.vec3, device="cpu")
        t = wp.zeros(n, dtype=float, device="cpu")
        f = wp.zeros(n, dtype=int, device="cpu")
        b = wp.zeros(n, dtype=wp.vec3, device="cpu")
        launch_split(_ray_kernel, n, [self._mesh.id, o, d, float(max_t)], [t, f, b])
        face = f.numpy().astype(np.int64)
        return face >= 0, t.numpy().astype(np.float64), face, b.numpy().astype(np.float64)

    def edge_crossings(self, edges: np.ndarray, end_gap: float = 1e-3) -> np.ndarray:
        """(e,) int: for each edge (e, 2) between this mesh's own vertices, a triangle it passes
        through that shares no corner with it, or -1.

        Exact segment-triangle tests over the triangles whose bounding boxes overlap the
        edge's. end_gap (share of the edge length): crossings this close to either end do
        not count, and a corner this close to an end is that end (duplicated vertices).
        """
        E = np.ascontiguousarray(edges, dtype=np.int32).reshape(-1)
        n = len(E) // 2
        out = wp.zeros(n, dtype=int, device="cpu")
        if n:
            ends = wp.array(E, dtype=wp.int32, device="cpu")
            launch_split(_segment_kernel, n, [self._mesh.id, self._points, self._indices, ends, float(end_gap)], [out])
        return out.numpy().astype(np.int64)

    def overlapping_faces(self, pad: float = 0.0) -> np.ndarray:
        """(k, 2) int pairs i < j of faces sharing no vertex whose bounding boxes, grown by `pad`
        (the mesh's unit) on every side, overlap: the candidates of a self-intersection test."""
        m = len(self.F)
        args = [self._mesh.id, self._points, self._indices, float(pad)]
        counts = wp.zeros(m, dtype=int, device="cpu")
        none = wp.zeros(0, dtype=int, device="cpu")
        launch_split(_overlap_kernel, m, [*args, none, 0], [counts, none])
        offsets = np.concatenate([[0], np.cumsum(counts.numpy())]).astype(np.int64)
        if 2 * offsets[-1] > np.iinfo(np.int32).max:  # Warp's int: the kernel's indices would wrap
            raise ValueError(f"overlapping_faces: {offsets[-1]} pairs of boxes overlap, more than it can list")
        pairs = wp.zeros(2 * int(offsets[-1]), dtype=int, device="cpu")
        if offsets[-1]:
            launch_split(_overlap_kernel, m, [*args, wp.array(offsets[:-1].astype(np.int32), dtype=int, device="cpu"), 1],
                         [counts, pairs])
        return pairs.numpy().astype(np.int64).reshape(-1, 2)

    def closest_points(self, X: np.ndarray, max_dist: float = 1e6
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points to X (n, 3).

        Returns points (n, 3), distance (n,), face (n,) int (-1: none within max_dist),
        bary (n, 3).
        """
        n = len(X)
        p = wp.array(self._local(X), dtype=wp.vec3, device="cpu")
        f = wp.zeros(n, dtype=int, device="cpu")
        b = wp.zeros(n, dtype=wp.vec3, device="cpu")
        launch_split(_closest_kernel, n, [self._mesh.id, p, float(max_dist)], [f, b])
        face = f.numpy().astype(np.int64)
        bary = b.numpy().astype(np.float64)
        pts = np.full((n, 3), np.nan)
        ok = face >= 0
        pts[ok] = self._points_at(face[ok], bary[ok])
        dist = np.linalg.norm(pts - np.asarray(X, np.float64), axis=1)
        dist[~ok] = np.inf
        return pts, dist, face, bary

    def inside(self, X: np.ndarray, max_dist: float = 1e6) -> np.ndarray:
        """(n,) bool: which points X (n, 3) lie inside the mesh (closed, outward faces), by
        the angle-weighted normal at the closest point (exact for a watertight mesh up to
        float32 rounding at the surface); points farther than max_dist count as outside."""
        return self.signed_distances(X, max_dist) < 0.0

    def signed_distances(self, X: np.ndarray, max_dist: float = 1e6) -> np.ndarray:
        """(n,) distances of points X (n, 3) to the mesh, negative inside it (see inside());
        +inf for points farther than max_dist."""
        n = len(X)
        if n == 0:
            return np.zeros(0)
        p = wp.array(self._local(X), dtype=wp.vec3, device="cpu")
        out = wp.zeros(n, dtype=float, device="cpu")
        launch_split(_signed_distance_kernel, n, [self._mesh.id, p, float(max_dist)], [out])
        d = out.numpy().astype(np.float64)
        d[d > max_dist] = np.inf
        return d

    def bidirectional_hits(self, origins: np.ndarray, directions: np.ndarray, max_t: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The nearer of the hits along +direction and -direction.

        Returns hit (n,) bool, points (n, 3), face (n,) int, bary (n, 3).
        """
        h1, t1, f1, b1 = self.ray_hits(origins, directions, max_t)
        h2, t2, f2, b2 = self.ray_hits(origins, -np.asarray(directions), max_t)
        use2 = h2 & (~h1 | (t2 < t1))
        hit = h1 | h2
        face = np.where(use2, f2, f1)
        bary = np.where(use2[:, None], b2, b1)
        pts = np.full((len(origins), 3), np.nan)
        pts[hit] = self._points_at(face[hit], bary[hit])
        return hit, pts, face, bary
