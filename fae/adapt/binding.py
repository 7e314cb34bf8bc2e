"""Binding another mesh to the template's skin, once, for motion-vector transfer (paper 002 §3).

A mesh fae did not make (other topology, its own UVs) is animated by carrying the
template's per-vertex motion vectors over to it. What that needs is computed here, once
per target; each frame is then a batched 3x3 product and a sparse gather
(fae.animate.retarget).

    surface_frames(V, F)                  (n, 3, 3) local frames: columns x (horizontal), y (normal), z
    ring_extents(V, F, frames, rings)     (n, 3) extent of each vertex's k-ring along its frame's axes
    frame_transforms(P, X, F, ...)        (n, 3, 3) T = R_X S R_P^T per template vertex, (n, 3) scales
    pinned_to_points(X, F, face, bary, Q, reach)   X moved smoothly so that its points (face, bary) lie at Q
    bind_to_surface(Y, X, F, NY)          closest (facing) triangle, barycentric coordinates, distance per point
    coverage_weights(dist, near, far)     (n,) 1 near the template's surface, fading to 0 beyond
    gather_matrix(face, bary, weight, F, m)   (n, m) sparse: bound point's weighted corners
    welded_components(V, F)               (n,) connected component of each vertex, seams welded

The paper's transformation (eq. 5-9): at each vertex a local frame (y: the vertex normal,
x: horizontal in the tangent plane, z = x × y) on the generic model and on the individual
one; R maps one frame to the other, S = diag(sx, sy, sz) is the ratio of the local oriented
bounding boxes of the neighbourhood, and a motion vector m becomes T m with T = S·R. Here
the "individual" is the template fitted to the target (same topology, so both boxes hold
the same vertices: a ratio of sizes, not of tessellations) and T is written in the face
frame: T = F_X diag(s) F_P^T. Two departures, both for stability on real meshes: the box
is taken over the 2-ring (a 1-ring's box is a triangle's size and noisy), and its extent
along the normal, which measures curvature rather than size, is replaced by the geometric
mean of the two tangent ratios; the scales are clamped about their median and smoothed.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from fae.mesh import adjacency, vertex_normals

UP = np.array([0.0, 1.0, 0.0])
PIN_WEIGHT = 1e4  # of a pinned point's row against the smoothness term
SCALE_LIMITS = (0.5, 2.0)  # local scale kept within these factors of its median
SCALE_SMOOTHING = 3  # neighbour-averaging passes over the scales
NORMAL_SMOOTHING = 8  # neighbour-averaging passes over the normals the frames are built on


def _unit(X: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(X, axis=-1, keepdims=True)
    return X / np.maximum(n, 1e-300)


def surface_frames(V: np.ndarray, F: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
    """(n, 3, 3) float64 orthonormal frames, columns x, y, z: y the unit vertex normal, x
    horizontal (perpendicular to the face frame's up, +y) in the tangent plane, pointing
    towards +x where the surface faces +z, z = x × y. Where the normal is vertical the
    projection of +x is used for x. V (n, 3) any unit, F (m, 3); normals (n, 3) to use
    instead of the area-weighted vertex normals."""
    y = vertex_normals(V, F) if normals is None else _unit(np.asarray(normals, dtype=np.float64))
    x = np.cross(UP, y)
    flat = np.linalg.norm(x, axis=1) < 1e-6
    if flat.any():
        x[flat] = np.array([1.0, 0.0, 0.0]) - y[flat, :1] * y[flat]
        still = np.linalg.norm(x[flat], axis=1) < 1e-6
        x[np.flatnonzero(flat)[still]] = (0.0, 0.0, 1.0)
    x = _unit(x)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=2)


def ring_matrix(F: np.ndarray, n: int, rings: int = 2) -> sp.csr_matrix:
    """(n, n) 0/1 CSR: row i marks the vertices within `rings` edges of vertex i (itself included)."""
    A = adjacency(F, n) + sp.identity(n, format="csr")
    R = A.copy()
    for _ in range(rings - 1):
        R = R @ A
    R = R.tocsr()
    R.data[:] = 1.0
    R.sort_indices()
    return R


def ring_extents(V: np.ndarray, F: np.ndarray, frames: np.ndarray, rings: int = 2,
                 ring: sp.csr_matrix | None = None) -> np.ndarray:
    """(n, 3) the size of each vertex's oriented bounding box: the extent (max - min) of its
    `rings`-ring's vertices along the three axes of its frame (frames (n, 3, 3) columns, from
    surface_frames). V's unit. ring: a precomputed ring_matrix(F, n, rings)."""
    V = np.asarray(V, dtype=np.float64)
    n = len(V)
    R = ring_matrix(F, n, rings) if ring is None else ring
    rows = np.repeat(np.arange(n), np.diff(R.indptr))
    local = np.einsum("kdj,kd->kj", frames[rows], V[R.indices] - V[rows])
    starts = R.indptr[:-1]
    return np.maximum.reduceat(local, starts, axis=0) - np.minimum.reduceat(local, starts, axis=0)


def frame_transforms(P: np.ndarray, X: np.ndarray, F: np.ndarray, rings: int = 2, used: np.ndarray | None = None,
                     limits: tuple[float, float] = SCALE_LIMITS, smoothing: int = SCALE_SMOOTHING,
                     normal_smoothing: int = NORMAL_SMOOTHING) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex of a template P (n, 3) and its fitted copy X (n, 3) (same faces F (m, 3),
    same unit): T (n, 3, 3) with T m = the motion m (face frame, at P) turned into X's local
    frame and scaled by the local boxes (module docstring), and the scales (n, 3) along the
    frame's x, y (normal), z. used (n,) bool: the vertices whose scales set the median
    (default all). The frames stand on normals averaged `normal_smoothing` times over
    each vertex's neighbours, on both surfaces alike: a fit's small ripples would otherwise
    turn neighbouring motion vectors apart and crease the target."""
    P = np.asarray(P, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    n = len(P)
    ring = ring_matrix(F, n, rings)
    A = ring_matrix(F, n, 1)
    degree = np.asarray(A.sum(axis=1)).ravel()
    NP, NX = vertex_normals(P, F), vertex_normals(X, F)
    for _ in range(normal_smoothing):  # the frames turn with the surface's shape, not with a fit's ripples
        NP, NX = _unit(A @ NP), _unit(A @ NX)
    FP, FX = surface_frames(P, F, NP), surface_frames(X, F, NX)
    eP, eX = ring_extents(P, F, FP, ring=ring), ring_extents(X, F, FX, ring=ring)
    tangent = np.stack([eX[:, 0] / np.maximum(eP[:, 0], 1e-12), eX[:, 2] / np.maximum(eP[:, 2], 1e-12)], axis=1)
    real = (eP[:, 0] > 0) & (eP[:, 2] > 0) & np.all(np.isfinite(tangent), axis=1)
    sel = real if used is None else real & np.asarray(used, bool)
    median = float(np.median(tangent[sel])) if sel.any() else 1.0
    tangent = np.where(real[:, None], tangent, median)
    tangent = np.clip(tangent, limits[0] * median, limits[1] * median)
    for _ in range(smoothing):
        tangent = (A @ tangent) / degree[:, None]
    scale = np.column_stack([tangent[:, 0], np.sqrt(tangent[:, 0] * tangent[:, 1]), tangent[:, 1]])
    T = np.einsum("nij,nj,nkj->nik", FX, scale, FP)
    return T, scale


def pinned_to_points(X: np.ndarray, F: np.ndarray, face: np.ndarray, bary: np.ndarray, Q: np.ndarray,
                     reach: float) -> np.ndarray:
    """(n, 3) the surface X (n, 3), F (m, 3) moved so that its points (face (k,), bary (k, 3))
    lie at Q (k, 3): the smoothest displacement (least |L D|^2, L the graph Laplacian with
    coincident vertices welded, so it spreads along the surface and never across a slit
    such as the mouth's) that meets them and is zero on vertices farther than `reach`
    (X's unit) from every point. A fit's feature points are where its data let them be;
    this puts them where they were given, so that a binding through X pairs the given
    points with the template's own."""
    from fae.mesh import coincident_groups, group_means
    from scipy.spatial import cKDTree

    X = np.asarray(X, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    k, label = coincident_groups(X)
    W = group_means(X, label, k)
    FW = label[F]
    corners = FW[np.asarray(face, dtype=np.int64)]
    at = np.einsum("kj,kjd->kd", bary, W[corners])
    Q = np.asarray(Q, dtype=np.float64)
    free = cKDTree(at).query(W, distance_upper_bound=reach)[0] < np.inf
    FW = FW[(FW[:, 0] != FW[:, 1]) & (FW[:, 1] != FW[:, 2]) & (FW[:, 2] != FW[:, 0])]
    A = adjacency(FW, k)
    L = (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()
    B = sp.csr_matrix((np.asarray(bary, dtype=np.float64).ravel(), (np.repeat(np.arange(len(corners)), 3),
                                                                     corners.ravel())), shape=(len(corners), k))
    idx = np.flatnonzero(free)
    Lf, Bf = L[:, idx], B[:, idx]
    M = (Lf.T @ Lf + PIN_WEIGHT * (Bf.T @ Bf)).tocsc()
    D = np.zeros((k, 3))
    from scipy.sparse.linalg import splu

    D[idx] = splu(M + 1e-12 * sp.identity(len(idx), format="csc")).solve(PIN_WEIGHT * (Bf.T @ (Q - at)))
    return X + D[label]


DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                       *[[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]], dtype=np.float64)
DIRECTIONS /= np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)
FACING = 0.3  # a triangle faces a direction when its unit normal's dot with it exceeds this


def bind_to_surface(Y: np.ndarray, X: np.ndarray, F: np.ndarray, NY: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point Y (k, 3): the closest point of the surface X (n, 3), F (m, 3), as
    face (k,) int64, bary (k, 3) float64 and distance (k,) (Y's unit). With normals NY
    (k, 3), a point whose closest point faces the other way (the inside of an upper lip
    nearest the top of the lower one) takes the closest point among the triangles facing
    its normal's nearest of 14 directions (axes and diagonals) instead."""
    from fae.adapt.query import MeshQuery

    Y = np.asarray(Y, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    _, dist, face, bary = MeshQuery(X, F).closest_points(Y)
    if (face < 0).any():
        raise ValueError(f"bind_to_surface: {int((face < 0).sum())} points found no closest point on the surface")
    if NY is not None:
        NF = _unit(np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]]))
        NY = _unit(np.asarray(NY, dtype=np.float64))
        wrong = np.einsum("kd,kd->k", NF[face], NY) < 0.0
        pick = np.argmax(NY @ DIRECTIONS.T, axis=1)
        for d in np.unique(pick[wrong]):
            these = np.flatnonzero(wrong & (pick == d))
            faces = np.flatnonzero(NF @ DIRECTIONS[d] > FACING)
            if len(faces) == 0:
                continue
            _, dd, ff, bb = MeshQuery(X, F[faces]).closest_points(Y[these])
            ok = ff >= 0
            face[these[ok]], bary[these[ok]], dist[these[ok]] = faces[ff[ok]], bb[ok], dd[ok]
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    return face, bary, dist


def coverage_weights(dist: np.ndarray, near: float, far: float) -> np.ndarray:
    """(k,) in [0, 1]: 1 for distances up to `near`, 0 from `far` on, a smoothstep between
    (continuous over a surface, since the distance to another surface is)."""
    t = np.clip((np.asarray(dist, dtype=np.float64) - near) / max(far - near, 1e-12), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def gather_matrix(face: np.ndarray, bary: np.ndarray, weight: np.ndarray, F: np.ndarray, m: int) -> sp.csr_matrix:
    """(k, m) CSR: row i holds weight[i] x the barycentric coordinates bary[i] (3,) at the
    corners of triangle F[face[i]]; times a (m, 3) array of per-vertex values it gives the
    weighted value at each bound point."""
    k = len(face)
    cols = np.asarray(F, dtype=np.int64)[np.asarray(face, dtype=np.int64)].ravel()
    vals = (np.asarray(bary, dtype=np.float64) * np.asarray(weight, dtype=np.float64)[:, None]).ravel()
    M = sp.csr_matrix((vals, (np.repeat(np.arange(k), 3), cols)), shape=(k, m))
    M.sum_duplicates()
    return M


def welded_components(V: np.ndarray, F: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(n,) int64 label of the connected component of each vertex of V (n, 3), F (m, 3), with
    vertices closer than `tol` (V's unit, relative to the mesh's size) counted as one: texture
    seams split a surface's vertices without making it two pieces."""
    from scipy.sparse.csgraph import connected_components

    from fae.mesh import close_pairs

    V = np.asarray(V, dtype=np.float64)
    n = len(V)
    size = float(np.max(np.ptp(V, axis=0))) if n else 1.0
    pairs = close_pairs(V, tol * max(size, 1e-300))
    E = np.asarray(F, dtype=np.int64)
    rows = np.concatenate([E[:, 0], E[:, 1], E[:, 2], pairs[:, 0]])
    cols = np.concatenate([E[:, 1], E[:, 2], E[:, 0], pairs[:, 1]])
    G = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, label = connected_components(G, directed=False)
    return label.astype(np.int64)


SEAM_NORMAL_COS = 0.5  # coincident vertices whose one-sided normals differ more than 60 degrees stay apart


def seam_groups(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) int64 labels, shared by the vertices of V (n, 3), F (m, 3) that are one point of
    the surface split along a texture seam: coincident (fae.mesh.coincident_groups)
    and, each seen from its own triangles, facing the same way (within 60 degrees). Lips
    modelled closed but cut apart also coincide; they face each other (the upper lip's
    underside down, the lower's top up) and keep labels of their own, so they can part."""
    from fae.mesh import coincident_groups

    V = np.asarray(V, dtype=np.float64)
    n = len(V)
    _, label = coincident_groups(V)
    label = label.astype(np.int64)
    N = vertex_normals(V, F)
    k = int(label.max()) + 1 if n else 0
    # each group's first vertex speaks for it; a member facing elsewhere gets its own label
    first = np.full(k, -1, dtype=np.int64)
    order = np.arange(n)[::-1]
    first[label[order]] = order
    apart = np.einsum("ij,ij->i", N, N[first[label]]) < SEAM_NORMAL_COS
    label[apart] = k + np.arange(int(apart.sum()))
    return label
