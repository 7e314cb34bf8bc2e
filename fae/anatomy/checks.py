"""Geometric validity of a FaceModel: what the structure alone cannot tell.

    facemodel_problems(model) -> list[str]      one message per problem, [] when valid
    check_report(model) -> dict                  `fae template check`'s report (FAPU, parts, problems)

Checks: the skin is an oriented 2-manifold whose only open borders (if any) run through
the mouth, the eyelids or the bottom of the neck; it faces outward (`outward_share`: most of
its area faces away from its middle, not wound inside out); it does not cut through itself; no skin
vertex lies inside a bone and every bone lies inside the skin; linear muscles run inside
the soft tissue; every rigid part is closed; all 84 MPEG-4 feature points are present;
the mirror map is a pairing (mirror[mirror[i]] == i) and, for a head that claims to be
symmetric (claims_symmetry: the template), pairs each vertex with its reflection; regions
cover every vertex.
Helpers (`self_intersections`, `edge_problems`) take plain arrays, libigl-style.
"""

from __future__ import annotations

import numpy as np

from fae.io.facemodel import FaceModel
from fae.mesh import coincident_groups
from fae.mpeg4 import FEATURE_POINTS, fapu0_from_positions

MIRROR_TOLERANCE = 1e-5  # m: partners of a symmetric head are reflections up to float32 storage
# m: corners of two triangles this close are one corner to the self-intersection test: the
# generic head has a star of five vertices within 2 microns at each inner eye corner, whose
# zero-area triangles a fit leaves touching at a point, which no one can see
SHARED_CORNER = 1e-5
BOX_PAD = 1e-6  # m around each face's box in the broad phase (Warp's boxes are float32)
OPENING_REGIONS = ("lip_upper", "lip_lower", "mouth_cavity", "eyelid_upper_l", "eyelid_upper_r",
                   "eyelid_lower_l", "eyelid_lower_r", "neck")
_EPS = 1e-12


def edge_counts(F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges (e, 2), how many faces use each (e,), and how many use each direction twice (e,)."""
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64)
    key = np.sort(E, axis=1)
    edges, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    forward = (E[:, 0] < E[:, 1]).astype(np.int64)
    fwd = np.bincount(inverse, weights=forward, minlength=len(edges))
    same_direction = np.maximum(fwd, counts - fwd) > 1
    return edges, counts, same_direction


def edge_problems(F: np.ndarray, allowed_border: np.ndarray | None = None, name: str = "skin") -> list[str]:
    """Non-manifold edges, inconsistent orientation and open borders outside `allowed_border` (bool per vertex)."""
    problems = []
    edges, counts, same_direction = edge_counts(F)
    if np.any(counts > 2):
        problems.append(f"{name}: {int((counts > 2).sum())} edges are shared by more than two faces (non-manifold)")
    if np.any(same_direction & (counts == 2)):
        problems.append(f"{name}: {int((same_direction & (counts == 2)).sum())} edges join faces of opposite orientation")
    border = edges[counts == 1]
    if len(border):
        if allowed_border is None:
            problems.append(f"{name}: {len(border)} open border edges; expected a closed surface")
        else:
            bad = ~(allowed_border[border[:, 0]] & allowed_border[border[:, 1]])
            if np.any(bad):
                problems.append(f"{name}: {int(bad.sum())} open border edges outside the mouth, eyelids and neck "
                                f"(first at vertex {int(border[bad][0, 0])})")
    return problems


def _segments_hit_triangles(p0, p1, a, b, c) -> np.ndarray:
    """(k,) whether segment p0-p1 crosses triangle abc (all (k, 3)), Moller-Trumbore, strict interiors."""
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > _EPS
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p0 - a
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    tol = 1e-9
    return ok & (u > tol) & (v > tol) & (u + v < 1 - tol) & (t > tol) & (t < 1 - tol)


def self_intersections(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(k, 2) pairs of faces that share no corner (no vertex, nor one within SHARED_CORNER
    metres) and cut through each other."""
    from fae.adapt.query import MeshQuery

    if len(F) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    T = V[F]
    # broad phase: faces sharing no vertex whose boxes overlap (the Warp BVH over the skin, one
    # launch per core; an R-tree here took 0.7 s of a bust's adapt, 0.2 s of it holding the GIL)
    pairs = MeshQuery(V, F).overlapping_faces(pad=BOX_PAD)
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    corner = coincident_groups(V, SHARED_CORNER)[1][F]
    shared = (corner[i][:, :, None] == corner[j][:, None, :]).any(axis=(1, 2))
    i, j = i[~shared], j[~shared]
    hit = np.zeros(len(i), dtype=bool)
    for (s, t) in ((i, j), (j, i)):
        A, B = T[s], T[t]
        for k in range(3):
            hit |= _segments_hit_triangles(A[:, k], A[:, (k + 1) % 3], B[:, 0], B[:, 1], B[:, 2])
    return np.stack([i[hit], j[hit]], axis=1)


def points_inside(V: np.ndarray, F: np.ndarray, points: np.ndarray, expected: bool | None = None) -> np.ndarray:
    """(k,) bool: which points lie inside the closed mesh (V, F).

    A fast first answer from the nearest surface sample (face centroids and vertices) and
    its normal; points whose answer differs from `expected` (all points when it is None)
    are then decided exactly by ray parity, which is slow but runs on few points.
    """
    import trimesh

    points = np.asarray(points, dtype=np.float64)
    quick = _points_inside_quick(V, F, points)
    recheck = np.arange(len(points)) if expected is None else np.flatnonzero(quick != expected)
    if len(recheck):
        mesh = trimesh.Trimesh(V, F, process=False)
        quick[recheck] = np.asarray(mesh.contains(points[recheck]), dtype=bool)
    return quick


def _points_inside_quick(V: np.ndarray, F: np.ndarray, points: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    T = V[F]
    fn = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], fn)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), _EPS)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), _EPS)
    samples = np.concatenate([T.mean(axis=1), V])
    normals = np.concatenate([fn, vn])
    _, nearest = cKDTree(samples).query(np.asarray(points, dtype=np.float64))
    offset = np.asarray(points, dtype=np.float64) - samples[nearest]
    return np.einsum("ij,ij->i", offset, normals[nearest]) < 0.0


def claims_symmetry(model: FaceModel) -> bool:
    """Whether `model` says its skin is mirror-symmetric: meta["symmetric"] when present,
    else True for a head in its own frame (identity scan_transform, like the template).
    A personalized head keeps the template's mirror pairing (the runtime uses it to map
    left/right) but a person's face is not symmetric; fae adapt writes symmetric=False."""
    if "symmetric" in model.meta:
        return bool(model.meta["symmetric"])
    return bool(np.allclose(np.asarray(model.scan_transform, dtype=np.float64), np.eye(4)))


MIN_OUTWARD_SHARE = 0.5  # of the skin's area facing away from its middle (heads: 95-96 %; inside out: 5 %)


def outward_share(V: np.ndarray, F: np.ndarray) -> float:
    """Share (0..1) of a skin's area, V (n, 3), F (m, 3), whose normal points away from the
    skin's area-weighted middle (each triangle weighed by how squarely): a head's skin, mouth
    and nostrils included, 0.95-0.96; wound inside out, its render shows the back and every
    normal-based step (fit, binding, shading) turns against it."""
    from fae.mesh import triangle_normals

    n = triangle_normals(np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64))
    area = np.linalg.norm(n, axis=1)
    if len(F) == 0 or area.sum() <= 0.0 or not np.all(np.isfinite(n)):
        return 1.0  # nothing to tell (the other checks say what is wrong)
    c = np.asarray(V, dtype=np.float64)[np.asarray(F, dtype=np.int64)].mean(axis=1)
    d = c - np.average(c, axis=0, weights=area)
    facing = np.einsum("ij,ij->i", n, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300))
    return float(facing[facing > 0].sum() / max(np.abs(facing).sum(), 1e-300))


def facemodel_problems(model: FaceModel) -> list[str]:
    """Geometric problems of `model` (see module docstring); [] when it is a valid head."""
    problems: list[str] = []
    V, F = model.skin_vertices, model.skin_faces.astype(np.int64)
    n = len(V)

    names = list(model.region_names)
    if model.skin_region.shape != (n,) or (n and (model.skin_region.min() < 0 or model.skin_region.max() >= len(names))):
        problems.append("skin_region: expected one valid region index per skin vertex")
        allowed = np.zeros(n, dtype=bool)
    else:
        allowed = np.isin(np.asarray(names, dtype=object)[model.skin_region], OPENING_REGIONS)
        unused = [r for i, r in enumerate(names) if not np.any(model.skin_region == i)]
        if unused:
            problems.append(f"region_names: regions without vertices: {', '.join(unused)}")
    problems += edge_problems(F, allowed)
    outward = outward_share(V, F)
    if outward < MIN_OUTWARD_SHARE:
        problems.append(f"skin: only {outward * 100:.0f} % of its area faces away from the head's middle; expected "
                        f"at least {MIN_OUTWARD_SHARE * 100:.0f} % (its faces are wound inside out)")
    pairs = self_intersections(V, F)
    if len(pairs):
        problems.append(f"skin: {len(pairs)} pairs of faces intersect (first: faces {int(pairs[0, 0])} and {int(pairs[0, 1])})")

    for name, part in model.parts.items():
        if edge_problems(part.faces.astype(np.int64), None, name):
            problems.append(f"parts[{name!r}]: expected a closed, consistently oriented mesh")
    for bone in ("cranium", "mandible"):
        if bone not in model.parts:
            problems.append(f"parts: missing {bone!r}")
            continue
        BV, BF = model.mesh(bone)
        inside = points_inside(BV, BF.astype(np.int64), V, expected=False)
        if np.any(inside):
            problems.append(f"skin: {int(inside.sum())} skin vertices lie inside the {bone} "
                            f"(first: vertex {int(np.flatnonzero(inside)[0])})")
        outside = ~points_inside(V, F, BV[:: max(1, len(BV) // 2000)], expected=True)
        if np.any(outside):
            problems.append(f"parts[{bone!r}]: {int(outside.sum())} sampled vertices lie outside the skin")

    samples, owners = [], []
    for k, muscle in enumerate(model.muscles):
        if muscle.kind != "linear" or muscle.insertion is None:
            continue
        a = model.surface_point_position(muscle.attachment)
        b = model.surface_point_position(muscle.insertion)
        for t in (0.1, 0.3, 0.5, 0.7, 0.9):
            samples.append(a + t * (b - a))
            owners.append(k)
    if samples:
        inside = points_inside(V, F, np.asarray(samples), expected=True)
        bad = sorted({model.muscles[owners[i]].name for i in np.flatnonzero(~inside)})
        if bad:
            problems.append(f"muscles: leave the soft tissue: {', '.join(bad)}")
    for muscle in model.muscles:
        if muscle.kind == "linear" and muscle.attachment.part not in ("cranium", "mandible"):
            problems.append(f"muscles ({muscle.name}): attachment must lie on the cranium or mandible, not {muscle.attachment.part!r}")
        if muscle.insertion is not None and muscle.insertion.part != "skin":
            problems.append(f"muscles ({muscle.name}): insertion must lie on the skin, not {muscle.insertion.part!r}")

    missing = [p.name for p in FEATURE_POINTS if p.name not in model.feature_points]
    if missing:
        problems.append(f"feature_points: missing {', '.join(missing)}")

    mirror = model.skin_mirror.astype(np.int64)
    if mirror.shape != (n,) or (n and (mirror.min() < 0 or mirror.max() >= n)):
        problems.append("skin_mirror: expected one valid vertex index per skin vertex")
    else:
        unpaired = np.flatnonzero(mirror[mirror] != np.arange(n))
        if len(unpaired):
            problems.append(f"skin_mirror: expected a pairing (mirror[mirror[i]] == i); fails at {len(unpaired)} "
                            f"vertices (first: vertex {int(unpaired[0])})")
        if claims_symmetry(model):
            err = np.abs(V[mirror] * np.array([-1.0, 1.0, 1.0]) - V).max(initial=0.0)
            if err > MIRROR_TOLERANCE:
                problems.append(f"skin_mirror: partners are {err * 1e3:.3g} mm from each other's reflection "
                                f"(tolerance {MIRROR_TOLERANCE * 1e3:g} mm; the head claims to be symmetric)")
    return problems


def check_report(model) -> dict:
    """The report of `fae template check` for a loaded FaceModel (a dict that JSON takes):
    skin_vertex_count, feature_points (name -> [x, y, z] metres), fapu0 (name -> metres),
    muscles ([{name, kind}]), parts, regions, problems (one line each; empty: valid)."""
    from fae.io.facemodel_gltf import structural_problems

    problems = list(structural_problems(model))
    if not problems:
        problems += facemodel_problems(model)
    positions = {}
    fapu0 = {}
    try:
        positions = {name: [float(v) for v in p] for name, p in model.feature_point_positions().items()}
        fapu0 = fapu0_from_positions(model.feature_point_positions())
    except (KeyError, ValueError, IndexError) as exc:
        problems.append(f"feature_points: cannot measure FAPU: {exc}")
    return {
        "skin_vertex_count": model.skin_vertex_count,
        "feature_points": positions,
        "fapu0": fapu0,
        "muscles": [{"name": m.name, "kind": m.kind} for m in model.muscles],
        "parts": sorted(model.parts),
        "regions": list(model.region_names),
        "problems": problems,
    }
