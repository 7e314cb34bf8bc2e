"""Removing self-intersections a fit may leave in a surface with openings and folds.

A fitted skin can cut through itself where two sheets lie millimetres apart (the lips at
the mouth slit, eyelids over the eyeball, the ear against the scalp, the inside of the
mouth) and a correspondence pulled one sheet onto the other's scan. untangle() finds such
places and blends the fit back towards a safe surface (one known to be free of
intersections with the same topology, e.g. the global-RBF level or the template itself)
there, with a smooth transition, until nothing crosses. Given a reference shape (a bone's
template), it also blends away folds: neighbouring faces turned more than FOLD_ANGLE
further against each other than on the reference, which crumple a thin bone before any
two of its faces cut through each other.

    edge_crossings(V, F) -> (edges (k, 2), faces (k,))
    along_seams(V0, F, edges, faces) -> (k,) bool: crossings of an edge along its face's seam
    folded_pairs(V0, V, F) -> (face pairs (k, 2)) turned into folds against the reference V0
    untangle(F, X, X_safe) -> (X (n, 3), weight (n,))

edge_crossings tests each mesh edge as a segment against the triangles of the mesh's own
BVH (Warp) whose boxes its box overlaps: two triangles intersect exactly when an edge of
one passes through the other, so this finds every intersecting place (about 20 ms for the
27k edges of the generic head's skin on one core, against about a second for a general
pairwise test).
"""

from __future__ import annotations

import numpy as np

from fae.adapt.geometry import adjacency_matrix, per_face_normals, within
from fae.adapt.query import MeshQuery
from fae.mesh import edges as mesh_edges
from fae.mesh import triangle_pairs

_END_GAP = 1e-3  # of the edge length, kept off both ends (Warp works in float32)
FOLD_ANGLE = np.pi / 2  # radians two neighbouring faces may turn further against each other than on the reference
SEAM_GAP = 5e-5  # m: rest vertices this close are one place (a seam's two sides)


def edge_crossings(V: np.ndarray, F: np.ndarray, edges: np.ndarray | None = None,
                   query: MeshQuery | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Edges of mesh V (n, 3), F (m, 3) that pass through a triangle sharing no vertex with them.

    Returns the crossing edges (k, 2) and, for each, one triangle it crosses (k,).
    query: a MeshQuery of V, F, when already built (moved to V here).
    """
    V = np.asarray(V, dtype=np.float64)
    E = mesh_edges(F) if edges is None else np.asarray(edges, dtype=np.int64)
    if query is None:
        query = MeshQuery(V, F)
    elif query.V is not V:
        query.move(V)
    face = query.edge_crossings(E, _END_GAP)
    found = face >= 0
    return E[found], face[found]


def along_seams(V0: np.ndarray, F: np.ndarray, edges: np.ndarray, faces: np.ndarray,
                gap: float = SEAM_GAP) -> np.ndarray:
    """(k,) bool: crossings (edges (k, 2), faces (k,) from edge_crossings) whose edge, on the
    rest surface V0 (n, 3), has both ends within `gap` metres of corners of its face: it lies
    along one of the face's edges (two sheets joined by a seam of nearly coincident
    vertices, the mouth pouch's walls, meet there edge on edge) or is a sliver of an edge
    at one corner (a few tens of micrometres, between a vertex and its twin). Either way
    the slightest deformation moves it through the face by rounding alone. (edge_crossings
    reports one face an edge passes through; an edge marked here that also passed through
    another face far from its seam would go unseen, which only an edge lying on a seam
    at rest can.)"""
    if len(edges) == 0:
        return np.zeros(0, dtype=bool)
    V0 = np.asarray(V0, dtype=np.float64)
    ends = V0[np.asarray(edges)]  # (k, 2, 3)
    corners = V0[np.asarray(F)[np.asarray(faces)]]  # (k, 3, 3)
    d = np.linalg.norm(ends[:, :, None, :] - corners[:, None, :, :], axis=3).min(axis=2)  # (k, 2)
    return np.all(d <= gap, axis=1)


def dihedral_turns(V: np.ndarray, F: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(p,) radians between the normals of the face pairs (p, 2) of mesh V (n, 3), F (m, 3):
    0 where the two faces are flat, pi where they lie folded onto each other."""
    n = per_face_normals(V, F)
    return np.arccos(np.clip(np.einsum("pd,pd->p", n[pairs[:, 0]], n[pairs[:, 1]]), -1.0, 1.0))


def folded_pairs(V0: np.ndarray, V: np.ndarray, F: np.ndarray, pairs: np.ndarray | None = None,
                 angle: float = FOLD_ANGLE) -> np.ndarray:
    """(k, 2) face pairs of F (m, 3) whose turn on V (n, 3) exceeds their turn on the
    reference V0 (n, 3) by more than `angle` radians: a crease become a fold (which a
    self-intersection test misses until the two faces actually cut through each other).
    pairs: triangle_pairs(F), when already known."""
    P = triangle_pairs(F) if pairs is None else pairs
    return P[dihedral_turns(V, F, P) - dihedral_turns(V0, F, P) > angle]


def untangle(F: np.ndarray, X: np.ndarray, X_safe: np.ndarray, rings: int = 2, rounds: int = 12,
             edges: np.ndarray | None = None, reference: np.ndarray | None = None,
             query: MeshQuery | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Blend surface X (n, 3) towards X_safe (n, 3) (same faces F, free of intersections)
    around every crossing, until none is left.

    Each round gives weight 0 to the vertices of crossing edges and triangles and `rings`
    rings around them, and lets the weight rise back to 1 over as many further rings.
    Returns the result (n, 3) = X_safe + weight (X - X_safe) and the weight (n,) in [0, 1]
    (1: the fit kept, 0: the safe surface). edges: mesh_edges(F), when already known.
    reference (n, 3): the shape X was made from (a bone's template); when given, folds
    against it (folded_pairs) are blended away like crossings (X_safe must have none).
    query: a MeshQuery of the same faces to reuse (it is moved). Whatever still crosses
    after `rounds` rounds is left to the caller (check with edge_crossings).
    """
    F = np.asarray(F, dtype=np.int64)
    X = np.asarray(X, dtype=np.float64)
    X_safe = np.asarray(X_safe, dtype=np.float64)
    n = len(X)
    E = mesh_edges(F) if edges is None else edges
    pairs = None if reference is None else triangle_pairs(F)
    weight = np.ones(n)
    Y = X
    query = MeshQuery(X, F) if query is None else query
    A = None
    check = E  # the edges whose crossing can have changed since the last round
    for r in range(rounds + 1):
        bad_e, bad_f = edge_crossings(Y, F, check, query)
        folded = np.zeros((0, 2), dtype=np.int64) if pairs is None else folded_pairs(reference, Y, F, pairs)
        if len(bad_e) == 0 and len(folded) == 0:
            break
        if A is None:
            A = adjacency_matrix(F, n)
        bad = np.zeros(n, dtype=bool)
        bad[bad_e.ravel()] = True
        bad[F[bad_f].ravel()] = True
        bad[F[folded.ravel()].ravel()] = True
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
        Y_next = X_safe + weight[:, None] * (X - X_safe)
        moved = np.any(Y_next != Y, axis=1)
        Y = Y_next
        # what crossed stays checked; an edge through a moved triangle has an end within
        # twice the longest edge of that triangle's corners
        reach = 2.0 * float(np.max(np.linalg.norm(Y[E[:, 0]] - Y[E[:, 1]], axis=1)))
        check = E[(zone | within(Y, Y[moved], reach))[E].any(axis=1)]
    return Y, weight
