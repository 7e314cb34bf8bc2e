"""Signed-distance grids of the bones, computed once in each bone's own rest frame.

The skin's non-penetration test needs the distance to the skull and to the mandible for
every particle and substep; a closest-point query against a mesh costs ~100x a trilinear
lookup in a precomputed grid, so the grid is built once and only looked up per step: the distance is exact within
NEAR_BAND cells of the surface, signed by the mesh's normal there; farther out it comes from
a grid of half the resolution signed by the winding number (robust for meshes that are not
watertight), interpolated and lowered to stay a lower bound.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
from fae.warp_setup import launch_split, wp

# nothing here is differentiated: no adjoint code to compile
wp.set_module_options({"enable_backward": False})

# Grids already computed in this process, by mesh content and grid settings: every Player
# (one per client in `fae serve`) of the same head reuses them instead of spending seconds.
_GRID_CACHE: OrderedDict[bytes, tuple[np.ndarray, np.ndarray, float]] = OrderedDict()
_GRID_CACHE_SIZE = 8
GRID_PADDING = 0.01  # metres between a mesh's bounding box and its grid's
# samples within this many cells of the surface get its exact distance; farther ones the
# coarse grid's, interpolated (the coarse cell's diagonal is 3.5 cells: its sign holds there)
NEAR_BAND = 4.0
FAR_MARGIN = 1.5
# the winding number's accuracy (Warp's beta: clusters of triangles farther than this many
# of their radii count as one dipole). It signs only the coarse samples, whose sign matters
# NEAR_BAND cells and more from the surface: 1.0 signs every coarse sample of the four
# heads' bones as Warp's default 2.0 does, in 55 % of the time (a bust's cranium grid took
# 0.81 s of fae adapt, 0.64 s of it the winding numbers; now 0.36 s)
WINDING_ACCURACY = 1.0


@wp.func
def _grid_point(tid: int, origin: wp.vec3, spacing: float, ny: int, nz: int):
    # sample `tid` of a grid stored x-major: (i, j, k) -> i * ny * nz + j * nz + k
    i = tid // (ny * nz)
    j = (tid // nz) % ny
    k = tid % nz
    return origin + wp.vec3(float(i), float(j), float(k)) * spacing


@wp.kernel
def _grid_near_signed_distance(mesh: wp.uint64, origin: wp.vec3, spacing: float, ny: int, nz: int,
                               band: float, first: int, out: wp.array(dtype=float)):
    # within `band` of the surface: exact distance, signed by the normal there; farther
    # samples are left as they are (filled from the coarse grid). Samples from `first` on.
    tid = wp.tid() + first
    p = _grid_point(tid, origin, spacing, ny, nz)
    query = wp.mesh_query_point_sign_normal(mesh, p, band, 1.0e-6)
    if query.result:
        cp = wp.mesh_eval_position(mesh, query.face, query.u, query.v)
        d = wp.length(p - cp)
        if d < band:
            out[tid] = d * query.sign


@wp.kernel
def _grid_signed_distance(mesh: wp.uint64, origin: wp.vec3, spacing: float, ny: int, nz: int,
                          max_dist: float, accuracy: float, first: int, out: wp.array(dtype=float)):
    tid = wp.tid() + first
    p = _grid_point(tid, origin, spacing, ny, nz)
    query = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist, accuracy, 0.5)
    if query.result:
        cp = wp.mesh_eval_position(mesh, query.face, query.u, query.v)
        out[tid] = wp.length(p - cp) * query.sign
    else:
        out[tid] = max_dist


def signed_distance_grid(V: np.ndarray, F: np.ndarray, cell: float = 0.003, max_cells: int = 96,
                         device: str = "cpu") -> tuple[np.ndarray, np.ndarray, float]:
    """Signed distance to the triangle mesh (V, F) sampled on a regular grid.

    V (n, 3) float64 metres, F (m, 3) int. The grid covers the mesh's bounding box plus
    GRID_PADDING metres, with cubic cells of `cell` metres (coarsened so that no axis has
    more than `max_cells` samples); outside it, a point's distance to the grid's box plus
    GRID_PADDING is a lower bound of its distance to the mesh (what the samplers return).

    Returns (values (nx, ny, nz) float32 metres, negative inside; origin (3,) float64
    metres, the position of values[0, 0, 0]; spacing float metres).
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int32)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise ValueError(f"signed_distance_grid: expected V (n, 3) and F (m, 3), got {V.shape} and {F.shape}")
    key = hashlib.blake2b(V.tobytes() + F.tobytes() + repr((V.shape, F.shape, cell, max_cells,
                                                            str(device))).encode(), digest_size=20).digest()
    if key in _GRID_CACHE:
        _GRID_CACHE.move_to_end(key)
        return _GRID_CACHE[key]
    lo = V.min(axis=0) - GRID_PADDING
    hi = V.max(axis=0) + GRID_PADDING
    spacing = max(cell, float((hi - lo).max()) / (max_cells - 1))
    dims = np.ceil((hi - lo) / spacing).astype(int) + 1
    mesh = wp.Mesh(points=wp.array(V.astype(np.float32), dtype=wp.vec3, device=device),
                   indices=wp.array(F.reshape(-1), dtype=wp.int32, device=device),
                   support_winding_number=True)
    max_dist = float(np.linalg.norm(hi - lo))
    # The winding number (robust where the mesh has holes) on every other sample only, the
    # exact distance near the surface on all: a third of the time of the winding number on all
    coarse_dims = (dims + 1) // 2
    coarse = wp.zeros(int(np.prod(coarse_dims)), dtype=float, device=device)
    launch_split(_grid_signed_distance, coarse.shape[0],
                 [mesh.id, wp.vec3(*lo.astype(np.float32)), float(2.0 * spacing), int(coarse_dims[1]),
                  int(coarse_dims[2]), max_dist, WINDING_ACCURACY], [coarse], device)
    far = _upsampled(coarse.numpy().reshape(tuple(coarse_dims)), dims)
    # interpolation overshoots by up to about a cell where the distance bends (the medial
    # axis, deep inside or far out): far samples are lowered so that they stay lower bounds
    # (a particle's clearance), by nothing at the band's edge rising to FAR_MARGIN cells one
    # band further (the field keeps growing outwards: a push still points out of the bone)
    band = NEAR_BAND * spacing
    depth = np.abs(far)
    far = np.sign(far) * (depth - FAR_MARGIN * spacing * np.clip((depth - band) / band, 0.0, 1.0))
    out = wp.array(far.astype(np.float32).ravel(), dtype=float, device=device)
    launch_split(_grid_near_signed_distance, out.shape[0],
                 [mesh.id, wp.vec3(*lo.astype(np.float32)), float(spacing), int(dims[1]), int(dims[2]),
                  float(band)], [out], device)
    values = out.numpy().reshape(tuple(dims)).copy()
    values.setflags(write=False)  # shared by every caller through the cache
    lo.setflags(write=False)
    _GRID_CACHE[key] = (values, lo, float(spacing))
    while len(_GRID_CACHE) > _GRID_CACHE_SIZE:
        _GRID_CACHE.popitem(last=False)
    return _GRID_CACHE[key]


def _upsampled(coarse: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """(dims) float32: a grid sampled on every other node, trilinearly interpolated."""
    out = np.asarray(coarse, dtype=np.float32)
    for axis, n in enumerate(dims):
        idx = np.arange(n) / 2.0
        i0 = np.minimum(np.floor(idx).astype(int), out.shape[axis] - 1)
        i1 = np.minimum(i0 + 1, out.shape[axis] - 1)
        f = (idx - i0).astype(np.float32)
        shape = [1] * out.ndim
        shape[axis] = n
        out = np.take(out, i0, axis=axis) * (1 - f).reshape(shape) + np.take(out, i1, axis=axis) * f.reshape(shape)
    return out


def sample_grid(values: np.ndarray, origin: np.ndarray, spacing: float, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear signed distance and its gradient at `points` (n, 3) metres (numpy).

    Points outside the grid get a lower bound of their distance (to the grid's box, plus
    GRID_PADDING; 1 m for a NaN point) and a zero gradient.
    Returns (phi (n,) metres, grad (n, 3)).
    """
    dims = np.array(values.shape)
    points = np.asarray(points, dtype=np.float64)
    g = (points - origin) / spacing
    inside = np.all((g >= 0.0) & (g <= dims - 1.000001), axis=1)  # NaN is outside
    gi = np.clip(np.nan_to_num(g), 0.0, dims - 1.000001)
    i0 = np.floor(gi).astype(int)
    f = gi - i0
    phi = np.zeros(len(g))
    grad = np.zeros((len(g), 3))
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1.0 - f[:, 0]
        sx = 1.0 if dx else -1.0
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1.0 - f[:, 1]
            sy = 1.0 if dy else -1.0
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1.0 - f[:, 2]
                sz = 1.0 if dz else -1.0
                v = values[i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz].astype(np.float64)
                phi += wx * wy * wz * v
                grad[:, 0] += sx * wy * wz * v
                grad[:, 1] += wx * sy * wz * v
                grad[:, 2] += wx * wy * sz * v
    grad /= spacing
    hi = origin + (dims - 1) * spacing
    away = np.linalg.norm(np.maximum(np.maximum(origin - points, points - hi), 0.0), axis=1) + GRID_PADDING
    phi[~inside] = np.nan_to_num(away[~inside], nan=1.0)
    grad[~inside] = 0.0
    return phi, grad
