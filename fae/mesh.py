"""Triangle-mesh basics shared by every layer: edges, adjacency, normals, areas, boundaries.

Meshes are `V (n, 3) float` (any unit; metres inside the engine) and `F (m, 3) int`,
counter-clockwise seen from outside. Functions are pure: inputs are never modified.

    edges(F)                      (E, 2) unique undirected edges, smaller index first
    adjacency(F, n)               (n, n) symmetric 0/1 vertex adjacency (scipy CSR)
    adjacency_from_edges(n, E)    the same from an edge list
    triangle_normals(V, F)        (m, 3) unnormalised (length = twice the area)
    vertex_normals(V, F)          (n, 3) unit, area-weighted (see its rule for degenerate vertices)
    vertex_areas(V, F)            (n,) a third of the area of the triangles around each vertex
    boundary_edges(F)             (b, 2) directed edges used by one triangle only
    boundary_vertices(F, n)       (n,) bool, vertices on such an edge
"""

from __future__ import annotations

import itertools

import numpy as np
import scipy.sparse as sp


def _edge_keys(e: np.ndarray) -> tuple[np.ndarray, int]:
    """One int64 per undirected edge of e (k, 2) (i < j after sorting), and the base used:
    a row-wise unique on keys is several times faster than numpy's unique(axis=0)."""
    base = int(e.max()) + 1 if e.size else 1
    lo, hi = np.minimum(e[:, 0], e[:, 1]), np.maximum(e[:, 0], e[:, 1])
    return lo * base + hi, base


def edges(F: np.ndarray) -> np.ndarray:
    """(E, 2) int64 unique undirected edges (i < j) of triangles F (m, 3), sorted."""
    F = np.asarray(F, dtype=np.int64)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    keys, base = _edge_keys(e)
    keys = np.unique(keys)
    return np.column_stack([keys // base, keys % base])


def adjacency_from_edges(n: int, E: np.ndarray) -> sp.csr_matrix:
    """(n, n) float symmetric vertex adjacency (1.0 where an edge of E (k, 2) joins two vertices)."""
    E = np.asarray(E, dtype=np.int64).reshape(-1, 2)
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    A = (A + A.T).tocsr()
    A.data[:] = 1.0
    return A


def adjacency(F: np.ndarray, n: int) -> sp.csr_matrix:
    """(n, n) float symmetric 0/1 vertex adjacency of triangles F (m, 3) over n vertices."""
    return adjacency_from_edges(n, edges(F))


def triangle_pairs(F: np.ndarray, fans: bool = False) -> np.ndarray:
    """(p, 2) int64 pairs of triangles of F (m, 3) that share an edge used by exactly two
    triangles, sorted by edge; with `fans`, also every two of the triangles around an edge
    of three or more (a non-manifold fan), after those."""
    F = np.asarray(F, dtype=np.int64)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    face = np.tile(np.arange(len(F)), 3)
    key, _ = _edge_keys(E)
    order = np.argsort(key, kind="stable")
    key, face = key[order], face[order]
    same = np.flatnonzero(key[1:] == key[:-1])
    alone = np.ones(len(same), dtype=bool)  # not part of a run of three or more (non-manifold)
    alone &= np.r_[True, same[1:] != same[:-1] + 1] & np.r_[same[:-1] + 1 != same[1:], True]
    pairs = np.column_stack([face[same[alone]], face[same[alone] + 1]])
    if not fans or alone.all():
        return pairs
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], len(key)]
    fan = [face[s:e] for s, e in zip(starts, ends) if e - s > 2]
    extra = [np.array(list(itertools.combinations(f, 2)), dtype=np.int64) for f in fan]
    return np.concatenate([pairs, *extra])


def triangle_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 3) float64 unnormalised triangle normals (length = twice the area)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    a = V[F[:, 0]]
    return np.cross(V[F[:, 1]] - a, V[F[:, 2]] - a)


def vertex_normals(V: np.ndarray, F: np.ndarray, corner_index: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) float64 unit vertex normals: the area-weighted mean of the adjacent triangles'.

    One rule for a vertex on no triangle, or only on degenerate ones: the direction from the
    mesh's centroid to it, or +Z where that is zero too (every normal has unit length, as
    glTF requires and the renderer's lighting assumes). corner_index: `F.ravel()` as int64,
    precomputed by callers that run this every frame. Sums with `np.bincount` (a scatter-add
    about 2.5x faster than np.add.at).
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if corner_index is None:
        corner_index = F.ravel().astype(np.int64)
    face_n = triangle_normals(V, F)
    n = V.shape[0]
    N = np.empty((n, 3))
    for k in range(3):
        N[:, k] = np.bincount(corner_index, weights=np.repeat(face_n[:, k], 3), minlength=n)
    length = np.sqrt(np.einsum("ij,ij->i", N, N))
    flat = length <= 1e-30
    if np.any(flat):
        radial = V[flat] - V.mean(axis=0)
        radial_length = np.linalg.norm(radial, axis=1)
        radial[radial_length <= 1e-30] = (0.0, 0.0, 1.0)
        radial_length[radial_length <= 1e-30] = 1.0
        N[flat] = radial / radial_length[:, None]
        length[flat] = 1.0
    return N / length[:, None]


def vertex_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) a third of the area of the triangles around each vertex (V's unit squared)."""
    a = 0.5 * np.linalg.norm(triangle_normals(V, F), axis=1)
    return np.bincount(np.asarray(F, dtype=np.int64).reshape(-1), weights=np.repeat(a / 3.0, 3), minlength=len(V))


def boundary_edges(F: np.ndarray) -> np.ndarray:
    """(b, 2) directed edges (as their triangle lists them) used by exactly one triangle."""
    F = np.asarray(F, dtype=np.int64)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    _, inverse, counts = np.unique(_edge_keys(E)[0], return_inverse=True, return_counts=True)
    return E[counts[inverse.ravel()] == 1]


def boundary_vertices(F: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: vertices on a boundary edge (an edge used by one triangle only)."""
    out = np.zeros(n, dtype=bool)
    out[boundary_edges(F).ravel()] = True
    return out


def wrapped_seam(F: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texture coordinates that wrap around in u (a cylindrical map, u in [0, 1]) without
    the seam's triangles interpolating across the whole texture.

    A triangle whose corners' u span more than half the texture, and that those corners
    moved by +1 make at least twice as narrow, crosses the seam: its corners with u < 0.5
    are replaced by copies of their vertices with u + 1 (sampled with
    u wrapping around, GL_REPEAT). F (m, 3) int, uv (n, 2). Returns (F2 (m, 3) int64 into
    the n + k vertices, source (k,) int64: the vertex each copy repeats, uv2 (n + k, 2)
    float32). Nothing changes (k = 0) when no triangle crosses the seam.
    """
    F = np.asarray(F, dtype=np.int64)
    uv = np.asarray(uv, dtype=np.float32)
    u = uv[F, 0]
    span = u.max(axis=1) - u.min(axis=1)
    wrapped = np.where(u < 0.5, u + 1.0, u)
    # and wrapping it makes it at least twice as narrow: a large triangle of an atlas's chart
    # (u 0.1, 0.7, 0.75) is drawn where it is
    crossing = (span > 0.5) & (wrapped.max(axis=1) - wrapped.min(axis=1) < 0.5 * span)
    low = crossing[:, None] & (u < 0.5)
    source = np.unique(F[low])
    F2 = F.copy()
    if len(source):
        copy_of = np.full(len(uv), -1, dtype=np.int64)
        copy_of[source] = len(uv) + np.arange(len(source))
        F2[low] = copy_of[F[low]]
    uv2 = np.concatenate([uv, uv[source] + np.array([1.0, 0.0], dtype=np.float32)])
    return F2, source, uv2


def seamed_surface(V: np.ndarray, F: np.ndarray, uv: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The surface V (n, 3), F (m, 3) with the copies wrapped_seam asks for, ready to draw
    with its texture: (V2 (n + k, 3), F2 (m, 3), uv2 (n + k, 2), N2 (n + k, 3) unit normals
    of the whole surface, each copy sharing its vertex's, seam (k,) the vertex each copy
    repeats)."""
    V = np.asarray(V, dtype=np.float64)
    F2, seam, uv2 = wrapped_seam(F, uv)
    N = vertex_normals(V, F)
    return np.concatenate([V, V[seam]]), F2, uv2, np.concatenate([N, N[seam]]), seam


def close_pairs(V: np.ndarray, tol: float) -> np.ndarray:
    """(p, 2) int64 pairs of points of V (n, 3) closer than `tol` (V's unit) that, chained,
    join every such group: each point to the first of its exact copies, and the distinct
    points to each other. All pairs of k copies of one point are k^2 / 2 (40,000 unused
    vertices at one point asked for 800 million and the process was killed)."""
    from scipy.spatial import cKDTree

    V = np.asarray(V, dtype=np.float64).reshape(-1, 3)
    if len(V) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    U, first, copy_of = np.unique(V, axis=0, return_index=True, return_inverse=True)
    copy_of = copy_of.ravel()
    copies = np.flatnonzero(first[copy_of] != np.arange(len(V)))
    near = cKDTree(U).query_pairs(tol, output_type="ndarray") if len(U) > 1 else np.zeros((0, 2), int)
    return np.concatenate([np.column_stack([copies, first[copy_of[copies]]]),
                           first[near].reshape(-1, 2)]).astype(np.int64)


def coincident_groups(V: np.ndarray, tol: float = 1e-7) -> tuple[int, np.ndarray]:
    """Groups of points of V (n, 3) closer than `tol` metres (chained): the number of groups
    k and each point's group label (n,) in 0..k-1."""
    from scipy.sparse.csgraph import connected_components

    V = np.asarray(V, dtype=np.float64)
    pairs = close_pairs(V, tol)
    g = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(V), len(V)))
    return connected_components(g, directed=False)


def group_means(X: np.ndarray, label: np.ndarray, k: int) -> np.ndarray:
    """(k, d): the mean of the rows of X (n, d) in each group of `label` (n,)."""
    X = np.asarray(X, dtype=np.float64).reshape(len(X), -1)
    count = np.bincount(label, minlength=k)[:, None]
    return np.column_stack([np.bincount(label, X[:, a], minlength=k) for a in range(X.shape[1])]) / count
