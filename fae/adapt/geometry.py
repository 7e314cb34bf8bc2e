"""Mesh quantities the fitting needs: normals, boundary, cotangent Laplacian, mean curvature.

libigl-style: arrays in, arrays out. V (n, 3) float64 metres, F (m, 3) int. The per-face
sums of the cotangent Laplacian and vertex areas run as float64 Warp kernels on the CPU: a
scan has 100k+ faces, and numpy's gathers cost 10-20x as much. Edges, adjacency, normals
and boundaries come from fae.mesh (one rule for every layer).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from fae.warp_setup import wp

from fae.adapt.query import init_warp
# the mesh basics live in fae.mesh; the fitting's modules import them from here by these names
from fae.mesh import adjacency as adjacency_matrix, boundary_vertices  # noqa: F401
from fae.mesh import triangle_normals as face_normal_vectors, vertex_normals as per_vertex_normals  # noqa: F401

# nothing here is differentiated: no adjoint code to compile
wp.set_module_options({"enable_backward": False})


@wp.kernel
def _face_sums_kernel(V: wp.array(dtype=wp.vec3d), F: wp.array(dtype=wp.int32), normal: wp.array(dtype=wp.vec3d),
                      laplacian: wp.array(dtype=wp.vec3d), area: wp.array(dtype=wp.float64), cotangents: int):
    # face f adds its normal vector (twice its area) to its corners; with cotangents, also a
    # third of its area and, for each edge ij, w (V_j - V_i) to i and w (V_i - V_j) to j,
    # w half the cotangent of the angle opposite
    f = wp.tid()
    a = F[3 * f]
    b = F[3 * f + 1]
    c = F[3 * f + 2]
    n = wp.cross(V[b] - V[a], V[c] - V[a])
    wp.atomic_add(normal, a, n)
    wp.atomic_add(normal, b, n)
    wp.atomic_add(normal, c, n)
    if cotangents == 0:
        return
    area2 = wp.max(wp.length(n), wp.float64(1.0e-300))
    third = area2 / wp.float64(6.0)
    wp.atomic_add(area, a, third)
    wp.atomic_add(area, b, third)
    wp.atomic_add(area, c, third)
    ea = V[c] - V[b]  # opposite corner a
    eb = V[a] - V[c]  # opposite corner b
    ec = V[b] - V[a]  # opposite corner c
    half = wp.float64(0.5) / area2
    wa = -wp.dot(eb, ec) * half
    wb = -wp.dot(ec, ea) * half
    wc = -wp.dot(ea, eb) * half
    wp.atomic_add(laplacian, b, wa * ea)
    wp.atomic_sub(laplacian, c, wa * ea)
    wp.atomic_add(laplacian, c, wb * eb)
    wp.atomic_sub(laplacian, a, wb * eb)
    wp.atomic_add(laplacian, a, wc * ec)
    wp.atomic_sub(laplacian, b, wc * ec)


def _face_sums(V: np.ndarray, F: np.ndarray, cotangents: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-vertex sums over faces: normal vectors (n, 3), cotangent Laplacian L V (n, 3) and
    barycentric areas (n,) (the last two zero unless `cotangents`)."""
    init_warp()
    n = len(V)
    v = wp.array(np.ascontiguousarray(V, dtype=np.float64), dtype=wp.vec3d, device="cpu")
    f = wp.array(np.ascontiguousarray(F, dtype=np.int32).reshape(-1), dtype=wp.int32, device="cpu")
    normal = wp.zeros(n, dtype=wp.vec3d, device="cpu")
    laplacian = wp.zeros(n if cotangents else 0, dtype=wp.vec3d, device="cpu")
    area = wp.zeros(n if cotangents else 0, dtype=wp.float64, device="cpu")
    if len(F):
        wp.launch(_face_sums_kernel, dim=len(F), inputs=[v, f, normal, laplacian, area, int(cotangents)],
                  device="cpu")
    return normal.numpy(), laplacian.numpy(), area.numpy()


def per_face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 3) unit face normals."""
    return _unit_rows(face_normal_vectors(V, F))


def _unit_rows(X: np.ndarray) -> np.ndarray:
    return X / np.maximum(np.sqrt(np.einsum("nd,nd->n", X, X)), 1e-300)[:, None]


def within(X: np.ndarray, Y: np.ndarray, radius: float) -> np.ndarray:
    """(n,) bool: which points X (n, 3) have a point of Y (k, 3) within `radius` (same unit)."""
    from scipy.spatial import cKDTree

    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    Y = np.asarray(Y, dtype=np.float64).reshape(-1, 3)
    if len(X) == 0 or len(Y) == 0:
        return np.zeros(len(X), dtype=bool)
    d, _ = cKDTree(Y).query(X, distance_upper_bound=radius * (1.0 + 1e-12))
    return np.isfinite(d)


def cotangent_laplacian_of(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n, 3) L V for the cotangent Laplacian L of mesh V (n, 3), F (m, 3)
    (L_ij = (cot a_ij + cot b_ij) / 2, rows summing to 0), without forming L."""
    return _face_sums(V, F, cotangents=True)[1]


def massmatrix(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) barycentric vertex areas (one third of the incident triangle areas)."""
    return _face_sums(V, F, cotangents=True)[2]


def mean_curvature(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) mean curvature (1/metres), Meyer et al.: H = |M^-1 L V| / 2 (paper 000 appendix).

    Positive where the surface bulges outwards along the vertex normal, negative in folds.
    """
    normal, LV, mass = _face_sums(V, F, cotangents=True)
    HN = -LV / np.maximum(mass, 1e-300)[:, None]
    return 0.5 * np.sign(np.einsum("nd,nd->n", HN, normal)) * np.linalg.norm(HN, axis=1)


def laplacian_lowpass(V: np.ndarray, F: np.ndarray, lam: float = 0.75, iterations: int = 1) -> np.ndarray:
    """(n, 3): V after `iterations` steps p <- p + lam * (mean of neighbours - p) (paper 001 eq. 3)."""
    A = adjacency_matrix(F, len(V))
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    W = sp.diags(1.0 / deg) @ A
    X = np.array(V, dtype=np.float64)
    for _ in range(iterations):
        X = X + lam * (W @ X - X)
    return X
