"""Removing self-intersections a fit may leave in a surface with openings and folds.

A fitted skin can cut through itself where two sheets lie millimetres apart (the lips at
the mouth slit, eyelids over the eyeball, the ear against the scalp, the inside of the
mouth) and a correspondence pulled one sheet onto the other's scan. untangle() finds such
places and blends the fit back towards a safe surface (one known to be free of
intersections with the same topology, e.g. the global-RBF level or the template itself)
there, with a smooth transition, until nothing crosses.

    edge_crossings(V, F) -> (edges (k, 2), faces (k,))
    untangle(F, X, X_safe) -> (X (n, 3), weight (n,))

edge_crossings casts each mesh edge as a ray segment against the mesh's own BVH (Warp):
two triangles intersect exactly when an edge of one passes through the other, so this
finds every intersecting place (a few ms for 27k edges, against about a second for a
general pairwise test).
"""

from __future__ import annotations

import numpy as np

from fae.adapt.geometry import adjacency_matrix
from fae.adapt.query import MeshQuery

_END_GAP = 1e-3  # of the edge length, kept off both ends (its own triangles; Warp works in float32)
_SAME_POINT = 1e-3  # of the edge length: a corner this close to an end is that end (duplicated vertices)
_MIN_EDGE = 1e-9  # m


def mesh_edges(F: np.ndarray) -> np.ndarray:
    """(e, 2) unique undirected edges of faces F (m, 3), smaller index first."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64), axis=1)
    return np.unique(E, axis=0)


def edge_crossings(V: np.ndarray, F: np.ndarray, edges: np.ndarray | None = None,
                   query: MeshQuery | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Edges of mesh V (n, 3), F (m, 3) that pass through a triangle sharing no vertex with them.

    Returns the crossing edges (k, 2) and, for each, one triangle it crosses (k,).
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    E = mesh_edges(F) if edges is None else edges
    q = MeshQuery(V, F) if query is None else query
    a, b = V[E[:, 0]], V[E[:, 1]]
    d = b - a
    length = np.linalg.norm(d, axis=1)
    ok = length > _MIN_EDGE  # zero-length edges (coincident vertices) cross nothing
    u = d / np.where(ok, length, 1.0)[:, None]
    found = np.zeros(len(E), dtype=bool)
    face = np.full(len(E), -1, dtype=np.int64)
    # both directions: the first hit from one end may be a triangle touching that end
    for origin, direction in ((a, u), (b, -u)):
        start = origin + direction * (_END_GAP * length)[:, None]
        hit, t, f, _ = q.ray_hits(start, direction, float(length.max(initial=0.0)))
        hit &= ok & (t < length * (1.0 - 2.0 * _END_GAP))
        corners = V[F[np.maximum(f, 0)]]  # (e, 3, 3); a corner at an end's position touches it
        gap = np.linalg.norm(corners[:, :, None, :] - np.stack([a, b], axis=1)[:, None, :, :], axis=3)
        touching = (gap <= _SAME_POINT * np.maximum(length, 1e-300)[:, None, None]).any(axis=(1, 2))
        new = hit & ~touching & ~found
        found |= new
        face[new] = f[new]
    return E[found], face[found]


def untangle(F: np.ndarray, X: np.ndarray, X_safe: np.ndarray, rings: int = 2, rounds: int = 12,
             edges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Blend surface X (n, 3) towards X_safe (n, 3) (same faces F, free of intersections)
    around every crossing, until none is left.

    Each round gives weight 0 to the vertices of crossing edges and triangles and `rings`
    rings around them, and lets the weight rise back to 1 over as many further rings.
    Returns the result (n, 3) = X_safe + weight (X - X_safe) and the weight (n,) in [0, 1]
    (1: the fit kept, 0: the safe surface). edges: mesh_edges(F), when already known. Whatever still crosses after `rounds` rounds
    is left to the caller (check with edge_crossings).
    """
    F = np.asarray(F, dtype=np.int64)
    X = np.asarray(X, dtype=np.float64)
    X_safe = np.asarray(X_safe, dtype=np.float64)
    n = len(X)
    A = adjacency_matrix(F, n)
    E = mesh_edges(F) if edges is None else edges
    weight = np.ones(n)
    Y = X
    for r in range(rounds + 1):
        bad_e, bad_f = edge_crossings(Y, F, E)
        if len(bad_e) == 0:
            break
        bad = np.zeros(n, dtype=bool)
        bad[bad_e.ravel()] = True
        bad[F[bad_f].ravel()] = True
        grow = rings + r // 3  # places that keep crossing get a wider blend
        for _ in range(grow):
            bad |= (A @ bad.astype(np.float64)) > 0
        target = np.where(bad, 0.0, 1.0)
        zone = bad
        for k in range(1, grow + 1):  # rise back to 1 over `grow` further rings
            ring = ((A @ zone.astype(np.float64)) > 0) & ~zone
            target[ring] = k / (grow + 1)
            zone = zone | ring
        weight = np.minimum(weight, target)
        Y = X_safe + weight[:, None] * (X - X_safe)
    return Y, weight
