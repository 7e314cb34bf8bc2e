"""More correspondence pairs per level (paper 000 §4.1): feature-mesh subdivision with ray
casting, and mean-curvature feature search on the scan.

The feature mesh is a Delaunay triangulation of the feature points in cylindrical
coordinates (azimuth about the vertical axis through the template's centre, height).
Each level subdivides it (midpoint 1-to-4 split, which keeps the samples evenly spread where
the paper's barycentre split would crowd them), and a ray along each new triangle's normal,
both ways, meets the current template and the scan; a pair is kept when both rays hit,
the hit normals are at most 90 degrees apart and the hits are within `max_distance`.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import Delaunay

from fae.adapt.errors import Surface
from fae.adapt.geometry import mean_curvature, per_face_normals

PAIR_COSINE = 0.7  # closest-point pairs: normals at most 45 degrees apart (concave folds such as behind the ears)


def feature_mesh(L: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(t, 3) int triangles over feature points L (k, 3), triangulated in (azimuth, height)
    about the vertical axis through `centre` (3,)."""
    rel = np.asarray(L, dtype=np.float64) - centre
    az = np.arctan2(rel[:, 0], rel[:, 2])
    radius = np.median(np.hypot(rel[:, 0], rel[:, 2]))
    uv = np.column_stack([az * radius, rel[:, 1]])
    if len(L) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    try:
        return np.asarray(Delaunay(uv).simplices, dtype=np.int64)
    except Exception:  # degenerate (collinear) feature points
        return np.zeros((0, 3), dtype=np.int64)


def feature_mesh_samples(L: np.ndarray, T: np.ndarray, level: int) -> tuple[np.ndarray, np.ndarray]:
    """Centres (s, 3) and unit normals (s, 3) of the feature mesh's triangles after `level`
    1-to-4 subdivisions (s = t * 4^level)."""
    V, F = np.asarray(L, dtype=np.float64), T
    if len(F) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    for _ in range(level):
        V, F = trimesh.remesh.subdivide(V, F)
    return V[F].mean(axis=1), per_face_normals(V, F)


def _hit_normals(s: Surface, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    N = np.einsum("nk,nkd->nd", bary, s.N[s.F[face]])
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)


def ray_pairs(origins: np.ndarray, directions: np.ndarray, model: Surface, scan: Surface,
              max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs where rays (both ways) from origins (s, 3) hit both the model and the scan.

    Returns model face (p,), model bary (p, 3), scan points (p, 3), accepted (s,) bool mask.
    """
    hm, pm, fm, bm = model.query.bidirectional_hits(origins, directions, max_distance)
    hs, ps, fs, bs = scan.query.bidirectional_hits(origins, directions, max_distance)
    ok = hm & hs
    idx = np.flatnonzero(ok)
    nm = _hit_normals(model, fm[idx], bm[idx])
    ns = _hit_normals(scan, fs[idx], bs[idx])
    good = (np.sum(nm * ns, 1) > 0.0) & (np.linalg.norm(pm[idx] - ps[idx], axis=1) < max_distance)
    good &= ~scan.face_on_boundary[fs[idx]]
    ok[idx[~good]] = False
    return fm[ok], bm[ok], ps[ok], ok


def curvature_features(scan: Surface, box_min: np.ndarray, box_max: np.ndarray, count: int,
                       spacing: float) -> np.ndarray:
    """(<= count,) indices of scan vertices with the largest |mean curvature| inside the box,
    off the boundary, at most one per cell of size `spacing` (paper 000 §4.1, Fig. 5)."""
    inside = np.all((scan.V >= box_min) & (scan.V <= box_max), axis=1) & ~scan.boundary
    cand = np.flatnonzero(inside)
    if len(cand) == 0:
        return cand
    # curvature on the faces around the box only (the rest of the scan is not searched)
    searched = np.any(inside[scan.F], axis=1)
    H = np.abs(mean_curvature(scan.V, scan.F[searched]))
    H[scan.F[~searched].ravel()] = 0.0  # the cut around the box is no feature
    top = min(count * 20, len(cand))
    cand = cand[np.argpartition(-H[cand], top - 1)[:top]]
    cand = cand[np.argsort(-H[cand])]
    cell = np.floor(scan.V[cand] / spacing).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    keep = cand[np.sort(first)]
    return keep[np.argsort(-H[keep])][:count]


def grid_sample(X: np.ndarray, spacing: float, candidates: np.ndarray | None = None) -> np.ndarray:
    """(s,) indices into X (n, 3): one point per occupied cube of side `spacing` metres
    (the first candidate in each), a cheap even subsample of a surface's vertices."""
    idx = np.arange(len(X)) if candidates is None else np.flatnonzero(candidates)
    if len(idx) == 0:
        return idx
    cell = np.floor(X[idx] / spacing).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    return idx[np.sort(first)]


def closest_pairs(X: np.ndarray, NX: np.ndarray, scan: Surface, max_distance: float,
                  samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest scan points to the model vertices X[samples] (normals NX), kept when compatible
    (normals at most 90 degrees apart, within max_distance, not on the scan's border).

    Returns the accepted sample indices (p,) and their scan points (p, 3). Used where the
    feature mesh does not reach (sides of the head, forehead, neck): each level's CSRBF then
    pulls the whole scanned area, not only the region between feature points.
    """
    pts, dist, face, bary = scan.query.closest_points(X[samples], max_distance)
    ok = face >= 0
    N = np.einsum("nk,nkd->nd", bary[ok], scan.N[scan.F[face[ok]]])
    good = np.sum(N * NX[samples[ok]], axis=1) > PAIR_COSINE
    good &= ~scan.face_on_boundary[face[ok]]
    keep = np.flatnonzero(ok)[good]
    return samples[keep], pts[keep]
