"""The template's skin carried onto a real scan without folding or tearing it.

    fit_to_scan(P, F, scan, movable, landmarks=None, stiffness=None) -> SurfaceFit

The scan is already in the face frame and cut to the head (fae.adapt.head_pose); the
template's seams (coincident vertices) are welded for the fit. Stages, each on the
output of the last:

1. Start (affine_to_scan): trimmed ICP of the template's visible skin onto the scan, one
   scale, rotation and translation (a full affine map would also stretch the neck that
   the scan cuts short); feature points, where given, start it and count in every step.
   A scan that covers only part of the head (a face, the front half: more than
   PARTIAL_EDGE_SHARE of the closest pairs land by its edge) pairs nothing with its edge:
   the template's back of the head, all paired with the rim of a face scan, pulled the
   start into it (the marble bust's front half: scale 0.84 where the whole bust is 1.0),
   and the crown then stayed small and was pulled into ridges towards the rim.
   Parts found on the scan apart from the face (the ears) are then carried there with the
   skin around them (`carry`), and placed by their feature points alone in the stiff
   stages (`placed`): the nearest scan to an ear that sits centimetres off is scalp.
2. Regularized non-rigid ICP (Amberg et al. 2007's idea, with a Laplacian instead of
   their per-vertex affine stiffness): per stiffness `a` of STIFFNESS, ROUNDS rounds of
       min_D  sum_i w_i |x_i + d_i - q_i|^2 + a^2 |S L D|^2 + f(a) w_L sum_k |b_k . (X + D) - l_k|^2
   over the displacement D (n, 3) of the skin X: q_i is vertex i projected onto the
   scan's tangent plane at its closest compatible scan point (normals within
   MAX_NORMAL_ANGLE, within a reach that shrinks stage by stage, not within EDGE_REACH of
   the scan's rim (PARTIAL_EDGE_REACH on a scan of part of the head: a face's outline) nor
   HOLE_REACH of a hole, where the template's surface goes on and the
   scan's does not; where the closest point is not compatible, the scan along the
   vertex's own normal, so that skin over a hollow follows its floor, not its steep side:
   scan_pairs); L is
   the graph Laplacian of the template mesh plus every pair of vertices closer than
   NEIGHBOUR_RADIUS (the mesh is irregular: slivers beside centimetre-long triangles), S a
   per-vertex stiffness (thin, creased parts bend as a piece); l_k are feature points
   bound to the skin by barycentric rows b_k, their weight f(a) fading with the stiffness
   (they place the parts, the scan gives the detail). Every matched vertex has a data row
   in every round (one that finds no pair is asked to stay), so a stage factors its
   sparse matrix once and solves x, y and z together. In the detail stages the scan
   pulls back where asked (`fill`, scan_pulls): each scan point pulls the skin's
   closest point towards itself, which reaches what the skin's own closest points never
   see (the rolled rim and the bowl of a real ear beside the template's plain dish);
   each vertex's target is its own pair and those pulls, averaged by weight.
3. No fold, no tear: a round's step may not fold a triangle (turn it more than FOLD_ANGLE
   from the template's) that the last round left whole: around any it does, the step is
   blended back (blend_away_folds), and the scan's pull is let go there (QUIET_RINGS
   rings): at once (it is asked to stay), and in the smoothness from the next stage on
   when let go in a stage's first round, else from the stage after (each stage's matrix is
   factored a stage ahead), so that the place then moves smoothly with its neighbours
   instead of being blended again; a stage may not make the skin cut through itself
   (an ear pressed into the scalp): it is blended back to the last stage there
   (fae.adapt.untangle, alternating with the fold blend: `whole`). So the last stage is
   always whole, and so is the result.
4. Skin farther than EXTEND_START from any skin the scan reaches (a neck below its cut,
   the back of the head on a face scan) takes the harmonic extension of the displacement
   around it from the start (harmonic_displacement over the same graph): smooth, where the
   stages left the blends' patchwork, and as the start placed it (the graph's weights do
   not carry the start's turn and scale, a linear field, unbent).
5. Projection (paper 001's local step): each matched vertex moves onto its closest
   compatible scan point within PROJECT_REACH, or part of the way where the whole way
   would turn one of its triangles (halved while it does), kept whole as in 3.

Skin no scanner sees (mouth, nostrils, behind the eyelids) has no data term anywhere and
follows its neighbours; `detail` limits which skin follows the scan in the soft stages.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from fae.adapt.calibration import apply_transform
from fae.linalg import symmetric_splu
from fae.adapt.errors import Surface
from fae.adapt.query import MeshQuery
from fae.adapt.untangle import mesh_edges, untangle
from fae.adapt.geometry import adjacency_matrix, face_normal_vectors, per_vertex_normals
from fae.mesh import boundary_edges, coincident_groups, group_means

STIFFNESS = (30.0, 12.0, 5.0, 2.0, 1.0, 0.5)  # a per stage, coarse to fine
NEIGHBOUR_RADIUS = 0.006  # m: vertices this close are neighbours in the smoothness term
SIMILARITY_START = True  # the start: one scale (True) or a full affine map
PARTIAL_EDGE_SHARE = 0.4  # of the start's closest pairs by the scan's rim: more, and the scan covers part of the head
# boundary loops at least this share of the longest one's length and of the widest one's
# extent are the scan's rim (not holes)
RIM_SHARE = 0.25
# and at least this share of the scan's diagonal in extent (the busts' head parts' cuts
# 0.42-0.59, face scans' outlines 0.87-0.92; holes, slits and eye openings 0.15-0.23)
RIM_MIN_EXTENT = 0.3
BLEND_RINGS = 1  # rings around a fold blended back to the last fold-free surface
BLEND_ROUNDS = 12  # rounds at most (the zone widens every second)
DETAIL_STIFFNESS = 5.0  # stages below this stiffness match only the `detail` skin
EXTEND_START = 0.01  # m: skin this far from any skin on the scan takes the harmonic extension
EDGE_REACH = 0.008  # m: scan faces this close to a whole head's rim (its cut below the neck) pair with nothing
# m: on a scan of part of the head (a face scan's outline), only those this close: the skin
# within 8 mm of a mask's edge kept the template's shape there, a step at the chin, jaw and
# brow (the meshmonk face 0.187 -> 0.089 % of the diagonal, the menpo3d mask 0.066 -> 0.046 %).
# A whole head's rim is its cut below the neck, where a nearer reach pulled Demosthenes' neck
# 9 mm and its cranium, carried with the skin, through the cheek
PARTIAL_EDGE_REACH = 0.004
# m: and those this close to a hole's edge: the template goes on past a rim for centimetres,
# but over a hole only as far as the hole is wide (a mask's mouth is a slit: within
# EDGE_REACH of it the lips paired nothing, and stayed 2-4 mm off the mask's lips)
HOLE_REACH = 0.002
QUIET_RINGS = 1  # rings around a fold whose scan pull is let go
ROUNDS = 3  # correspondence rounds per stiffness
REACH = (0.04, 0.004)  # m: pairs farther than this are dropped, from the first stage to the last
MAX_NORMAL_ANGLE = 60.0  # degrees between a vertex's and its scan point's normals
RAY_SHARE = 4.0  # a scan point along a vertex's normal is taken when at most this many times as far as the closest
LANDMARK_WEIGHT = 1.0  # of a feature point's row against a vertex's, at the stiffest stage
LANDMARK_FADE = 1.0  # the weight falls as (stiffness / the first stiffness) ** this
PROJECT_REACH = 0.004  # m: the last stage moves a vertex onto the scan when this close
PROJECT_TURN = 60.0  # degrees a triangle may turn in that move
PROJECT_HALVINGS = 6  # a move that turns a triangle further is halved at most this often,
PROJECT_REVERTS = 5  # then taken back (as often: taking one back can turn its neighbours')
FILL_WEIGHT = 2.0  # of a scan point's pull (scan_pulls) against a vertex's own pair (busts: 0.8-1.7 % nearer than 1 or 4)
FOLD_ANGLE = 90.0  # degrees: a triangle turned further than this from the template is folded
DEGENERATE_SHARE = 1e-4  # of the median triangle area: smaller triangles have no normal to fold


@dataclass
class SurfaceFit:
    """Result of fit_to_scan: vertices (n, 3) metres (the template's vertex order, seams
    unwelded again); affine (4, 4) the start (a similarity unless SIMILARITY_START is
    off); partial_scan: the scan covers only part of the head (affine_to_scan); stages: a report per stage (stiffness, reach, pairs, their RMS, folds left, skin
    let go, vertices blended and untangled, seconds since the start); folded: triangles
    folded against the template in the result (0 unless a blend ran out of rounds)."""

    vertices: np.ndarray
    affine: np.ndarray
    partial_scan: bool = False
    stages: list[dict] = field(default_factory=list)
    folded: int = 0


def fold_reference(X0: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference side of `folded_triangles` for X0 (n, 3), F (m, 3): ((m, 3) unit
    normals, (m,) bool triangles with a normal), for a caller that tests many surfaces
    against one reference (a fit tests 150)."""
    N0 = face_normal_vectors(X0, F)
    a0 = np.linalg.norm(N0, axis=1)
    return N0 / np.maximum(a0, 1e-300)[:, None], a0 > DEGENERATE_SHARE * np.median(a0)


def folded_triangles(X0: np.ndarray, X: np.ndarray, F: np.ndarray, angle: float = FOLD_ANGLE,
                     reference: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(m,) bool: triangles of F whose normal on X (n, 3) turned more than `angle` degrees
    from their normal on the reference X0 (n, 3). Triangles without a normal (area below
    DEGENERATE_SHARE of the median, on either surface: the template has collapsed ones
    at its seams) are never counted. reference: fold_reference(X0, F), made once."""
    U0, real0 = fold_reference(X0, F) if reference is None else reference
    # by components and squared lengths: a fit tests ~150 surfaces, this is 1.6x np.cross's way,
    # and gathering each coordinate by the corners (3, m) another 1.5x X[F]'s (n, 3) rows
    FT = F.T
    x, y, z = X[:, 0][FT], X[:, 1][FT], X[:, 2][FT]
    e1x, e1y, e1z = x[1] - x[0], y[1] - y[0], z[1] - z[0]
    e2x, e2y, e2z = x[2] - x[0], y[2] - y[0], z[2] - z[0]
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    area2 = nx * nx + ny * ny + nz * nz
    real = real0 & (area2 > DEGENERATE_SHARE ** 2 * np.median(area2))
    along = U0[:, 0] * nx + U0[:, 1] * ny + U0[:, 2] * nz
    return real & (along < np.cos(np.radians(angle)) * np.sqrt(area2))


def graph_laplacian(F: np.ndarray, n: int, P: np.ndarray | None = None, radius: float = 0.0) -> sp.csr_matrix:
    """(n, n) uniform graph Laplacian I - D^-1 A of the mesh F (m, 3); with points P (n, 3)
    and a radius (metres), every pair of vertices closer than that is a neighbour too, so
    the smoothness is the same over a dense patch of slivers as over a coarse one."""
    A = adjacency_matrix(F, n).astype(np.float64)
    if P is not None and radius > 0:
        pairs = cKDTree(P).query_pairs(radius, output_type="ndarray")
        A = A + sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        A = (A + A.T).tocsr()
    A.data[:] = 1.0
    deg = np.asarray(A.sum(axis=1)).ravel()
    return (sp.identity(n, format="csr") - sp.diags(1.0 / np.maximum(deg, 1.0)) @ A).tocsr()


def near_edge(scan: Surface, reach: float = EDGE_REACH) -> np.ndarray:
    """(m,) bool: faces of the scan within `reach` metres of its rim (where the scan or the
    head part ends: near_rim) or within HOLE_REACH of a hole. A template vertex whose
    closest point lies there has no counterpart on the scan: the surface it belongs to
    goes on where the scan stops. Cached on the Surface."""
    cached = getattr(scan, "_near_edge", None)
    if cached is not None and cached[0] == reach:
        return cached[1]
    near = near_rim(scan, reach) | _faces_near(scan, scan.boundary, HOLE_REACH)
    scan._near_edge = (reach, near)
    return near


def _faces_near(scan: Surface, at: np.ndarray, reach: float) -> np.ndarray:
    """(m,) bool: faces of the scan with a corner among `at` (n,) bool, or whose middle lies
    within `reach` metres of one of those vertices."""
    near = at[scan.F].any(axis=1)
    if at.any():
        d, _ = cKDTree(scan.V[at]).query(scan.V[scan.F].mean(axis=1))
        near |= d < reach
    return near


def near_rim(scan: Surface, reach: float = EDGE_REACH) -> np.ndarray:
    """(m,) bool: faces of the scan within `reach` metres of its rim: its boundary loops at
    least RIM_SHARE of the longest one's length and of the widest one's extent, and
    RIM_MIN_EXTENT of the scan's diagonal across (a face scan's outline, the head part's cut
    below the neck), not its holes (a bust with a hundred 5 mm holes behind is whole; a
    face scan's eye openings, a mouth's slit)."""
    from scipy.sparse.csgraph import connected_components

    edges = boundary_edges(scan.F)
    if len(edges) == 0:
        return np.zeros(len(scan.F), dtype=bool)
    n = len(scan.V)
    _, loop = connected_components(sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n)),
                                   directed=False)
    # a rim is large both in length and in extent (bounding-box diagonal): a face scan's eye
    # openings, cut along the lids' sawtooth, run half its outline's length within a fifth
    # of its extent; a mouth's slit spans more than a quarter of a bust's neck cut, in
    # under a quarter of its length
    ids = loop[edges[:, 0]]
    length = np.bincount(ids, weights=np.linalg.norm(scan.V[edges[:, 0]] - scan.V[edges[:, 1]], axis=1))
    lo = np.full((len(length), 3), np.inf)
    hi = np.full((len(length), 3), -np.inf)
    np.minimum.at(lo, ids, scan.V[edges[:, 0]])
    np.maximum.at(hi, ids, scan.V[edges[:, 0]])
    extent = np.linalg.norm(np.where(np.isfinite(hi - lo), hi - lo, 0.0), axis=1)
    rim = (length[ids] >= RIM_SHARE * length.max()) & (extent[ids] >= RIM_SHARE * extent.max())
    rim &= extent[ids] >= RIM_MIN_EXTENT * scan.diagonal  # a closed head's one mouth slit is no rim
    on_rim = np.zeros(n, dtype=bool)
    on_rim[edges[rim].ravel()] = True
    return _faces_near(scan, on_rim, reach)


def covers_part_of_head(X: np.ndarray, scan: Surface, keep: float = 0.8) -> bool:
    """Whether `scan` covers only part of the head whose skin points X (n, 3) metres are
    placed on it (a face, a front half): more than PARTIAL_EDGE_SHARE of the closest `keep`
    share of their closest scan points lie on faces by the scan's rim (near_rim)."""
    by_rim = np.zeros(len(scan.V), dtype=bool)
    by_rim[scan.F[near_rim(scan)].ravel()] = True
    d, j = scan.tree.query(X)
    return bool(np.mean(by_rim[j[d <= np.quantile(d, keep)]]) > PARTIAL_EDGE_SHARE)


def start_placement(P: np.ndarray, F: np.ndarray, scan: Surface, movable: np.ndarray,
                    landmarks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, bool]:
    """Where fit_to_scan's start first places the template on `scan`, and whether it will
    find that the scan covers part of the head only: affine_to_scan's first step ((4, 4)
    map, partial) for the template P (n, 3), F (m, 3), seams welded, placed by the feature
    points `landmarks` (faces (k,), bary (k, 3), scan points (k, 3)), its `movable` (n,)
    bool skin tested; for a caller that needs them before the fit (the ears, looked for
    around where the template's fall at the person's size, and not on a face scan's rim)."""
    P_in, F_in = np.asarray(P, dtype=np.float64), np.asarray(F, dtype=np.int64)
    n, label = coincident_groups(P_in)
    P = group_means(P_in, label, n)
    use = np.bincount(label, weights=np.asarray(movable, dtype=float), minlength=n) > 0
    points = None
    if landmarks is not None and len(landmarks[0]):
        on_template = np.einsum("kj,kjd->kd", landmarks[1], P[label[F_in[landmarks[0]]]])
        points = (on_template, np.asarray(landmarks[2], dtype=np.float64), np.ones(len(on_template)))
    return affine_to_scan(P, scan, use, iterations=1, points=points, similarity=SIMILARITY_START)


def scan_pairs(X: np.ndarray, NX: np.ndarray, scan: Surface, reach: float, candidates: np.ndarray,
               along_normal: bool = False, rays: np.ndarray | None = None,
               edge_reach: float = EDGE_REACH) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (k,) of X (n, 3) among `candidates` (n,) bool paired with their closest
    compatible scan points (k, 3): within `reach` metres, normals within
    MAX_NORMAL_ANGLE, not on a face at the scan's boundary. A vertex whose closest point
    is not compatible takes the scan along its own normal NX (n, 3) instead (the nearer
    hit either way), when that is compatible and at most RAY_SHARE times as far: a
    template's step over a scan's hollow (an inner eye corner sculpted deep) has its
    closest points on the hollow's steep side, and the floor under it is what it should
    follow (rays (n,) bool: the vertices that may; default all). along_normal: the target
    is the vertex's projection onto the scan's tangent plane there instead (point-to-plane:
    the data moves vertices across the surface, never along it, so they do not bunch up
    into slivers that flip). edge_reach: metres from the scan's rim within which its
    faces pair nothing (near_edge)."""
    idx = np.flatnonzero(candidates)
    pts, dist, face, bary = scan.query.closest_points(X[idx], reach)
    N = _scan_normals(scan, face, bary)
    cos_max = np.cos(np.radians(MAX_NORMAL_ANGLE))
    edge = near_edge(scan, edge_reach)
    ok = (face >= 0) & (np.sum(N * NX[idx], axis=1) >= cos_max)
    ok[ok] &= ~edge[face[ok]]
    miss = np.flatnonzero(~ok if rays is None else ~ok & rays[idx])
    if len(miss):
        hit, hit_pts, hit_face, hit_bary = scan.query.bidirectional_hits(X[idx[miss]], NX[idx[miss]], reach)
        hit_N = _scan_normals(scan, np.where(hit, hit_face, -1), hit_bary)
        near = np.where(np.isfinite(dist[miss]), dist[miss], reach) * RAY_SHARE
        good = hit & (np.sum(hit_N * NX[idx[miss]], axis=1) >= cos_max)
        good[good] &= ~edge[hit_face[good]]
        good[good] &= np.linalg.norm(hit_pts[good] - X[idx[miss[good]]], axis=1) <= near[good]
        taken = miss[good]
        pts[taken], N[taken], ok[taken] = hit_pts[good], hit_N[good], True
    if along_normal:
        pts = X[idx] + np.sum((pts - X[idx]) * N, axis=1, keepdims=True) * N
    return idx[ok], pts[ok]


def scan_pulls(X: np.ndarray, NX: np.ndarray, F: np.ndarray, skin: MeshQuery, scan: Surface, reach: float,
               fill: np.ndarray, edge_reach: float = EDGE_REACH) -> tuple[np.ndarray, np.ndarray]:
    """The scan's pull on the skin X (n, 3), F (m, 3): each scan vertex within `reach` metres
    of a skin triangle whose corners are all `fill` (n,) bool, with compatible normals
    (NX (n, 3)) and not near the scan's edge, pulls that triangle's closest point towards
    itself, shared among its corners by their barycentric weights. The skin's own pairs
    (scan_pairs) reach only what lies nearest the skin; these reach what the skin's shape
    lacks (an ear's rolled rim, the bowl of its concha). Returns the summed pulls (n, 3)
    metres and the summed weights (n,). skin: a MeshQuery of F, moved to X here."""
    n = len(X)
    skin.move(X)
    pts, dist, face, bary = skin.closest_points(scan.V, reach)
    ok = face >= 0
    ok[ok] &= fill[F[face[ok]]].all(axis=1)
    N = np.einsum("nk,nkd->nd", bary[ok], NX[F[face[ok]]])
    sel = np.flatnonzero(ok)
    good = np.sum(N * scan.N[sel], axis=1) >= np.cos(np.radians(MAX_NORMAL_ANGLE)) * np.linalg.norm(N, axis=1)
    sel = sel[good]
    vf = np.zeros(len(scan.V), dtype=bool)  # scan vertices on faces near its edge pull nothing
    vf[scan.F[near_edge(scan, edge_reach)].ravel()] = True
    sel = sel[~vf[sel]]
    corners, w = F[face[sel]].ravel(), bary[sel].ravel()
    pull = np.repeat(scan.V[sel] - pts[sel], 3, axis=0) * w[:, None]
    acc = np.stack([np.bincount(corners, weights=pull[:, k], minlength=n) for k in range(3)], axis=1)
    return acc, np.bincount(corners, weights=w, minlength=n)


def _scan_normals(scan: Surface, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(k, 3) unit normals of the scan at points given by face (k,) (-1: none, zero normal)
    and bary (k, 3)."""
    N = np.zeros((len(face), 3))
    ok = face >= 0
    N[ok] = np.einsum("nk,nkd->nd", bary[ok], scan.N[scan.F[face[ok]]])
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)


def affine_to_scan(X: np.ndarray, scan: Surface, use: np.ndarray, iterations: int = 15, keep: float = 0.8,
                   points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                   similarity: bool = False) -> tuple[np.ndarray, bool]:
    """((4, 4) affine map taking the vertices X[use] onto the scan by trimmed ICP (closest
    scan vertices; the closest `keep` share of pairs), partial): points: fixed pairs (template
    points (k, 3), scan points (k, 3), weights (k,)) that start it and count in every step,
    all k of them together as much as all the surface pairs, each in proportion to its
    weight. similarity: rotation, translation and
    one scale only (the neck below a scan's cut then keeps the template's proportions).
    partial: more than PARTIAL_EDGE_SHARE of the first step's kept pairs lie on faces by
    the scan's rim (near_rim: not its holes): the scan covers only part of the head (a
    face, a front half; the busts, cut below the neck: 16-26 %, a face 58-65 %), and no
    pair by its edge (near_edge) is kept, since the skin the scan lacks would pull the
    start into its rim. On a
    whole head those pairs are left in: the busts' faces fit 0.01-0.03 % of the diagonal
    worse without them."""
    A = np.eye(4)
    P = X[use]

    def solve(src, dst, weight):
        if similarity:  # Umeyama has no weights: a pair of weight w is repeated about w^2 times
            from fae.adapt.calibration import similarity_transform

            rep = np.maximum(1, np.round((weight / weight.min()) ** 2).astype(int))
            sc, R, t = similarity_transform(np.repeat(src, rep, axis=0), np.repeat(dst, rep, axis=0))
            out = np.eye(4)
            out[:3, :3] = sc * R
            out[:3, 3] = t
            return out
        H = np.c_[src, np.ones(len(src))] * weight[:, None]
        M, *_ = np.linalg.lstsq(H, dst * weight[:, None], rcond=None)
        out = np.eye(4)
        out[:3, :3] = M[:3].T
        out[:3, 3] = M[3]
        return out

    if points is not None:
        share = np.asarray(points[2], dtype=np.float64) / np.sum(points[2])
    if points is not None and len(points[0]) >= 4:
        A = solve(points[0], points[1], np.sqrt(share))
    by_edge = np.zeros(len(scan.V), dtype=bool)
    by_edge[scan.F[near_edge(scan)].ravel()] = True
    by_hole = np.zeros(len(scan.V), dtype=bool)  # by an edge, not by the rim: a hole's
    by_hole[scan.F[near_edge(scan) & ~near_rim(scan)].ravel()] = True
    partial = False
    for step in range(iterations):
        Y = apply_transform(A, P)
        d, j = scan.tree.query(Y)
        if step == 0:
            partial = covers_part_of_head(Y, scan, keep)
        inner = ~(by_edge if partial else by_hole)[j]
        if not inner.any():  # the whole template nearest the scan's rim: nothing else to go by
            inner[:] = True
        good = inner & (d <= np.quantile(d[inner], keep))
        src, dst, wt = P[good], scan.V[j[good]], np.ones(int(good.sum()))
        if points is not None and len(points[0]):
            src, dst = np.vstack([src, points[0]]), np.vstack([dst, points[1]])
            wt = np.r_[wt, np.sqrt(good.sum() * share)]
        A = solve(src, dst, wt)
    return A, partial


def blend_away_folds(P: np.ndarray, X_safe: np.ndarray, X: np.ndarray, F: np.ndarray,
                     ring: sp.csr_matrix | None = None, rounds: int | None = None,
                     reference: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, int]:
    """X (n, 3) blended back towards X_safe (n, 3) wherever it folds against the template P
    (n, 3): weight 0 on the folded triangles and BLEND_RINGS rings around them, rising back
    to 1 over as many rings (ring: adjacency_matrix(F, n)); repeated with wider zones while
    anything still folds. Where X_safe folds itself, the blend keeps that fold (it is the
    caller's job to pass a fold-free X_safe). Returns the result and how many vertices
    were blended. reference: fold_reference(P, F), if the caller has it."""
    n = len(P)
    ring = adjacency_matrix(F, n) if ring is None else ring
    weight = np.ones(n)
    Y = X
    for r in range(BLEND_ROUNDS if rounds is None else rounds):
        bad = folded_triangles(P, Y, F, reference=reference)
        if not bad.any():
            break
        zone = np.zeros(n, dtype=bool)
        zone[F[bad].ravel()] = True
        grow = BLEND_RINGS + r // 2
        for _ in range(grow):
            zone |= (ring @ zone.astype(np.float64)) > 0
        target = np.where(zone, 0.0, 1.0)
        edge = zone
        for k in range(1, grow + 1):
            band = ((ring @ edge.astype(np.float64)) > 0) & ~edge
            target[band] = k / (grow + 1)
            edge = edge | band
        weight = np.minimum(weight, target)
        Y = X_safe + weight[:, None] * (X - X_safe)
    return Y, int(np.sum(weight < 1.0))


def projected_part_way(X: np.ndarray, F: np.ndarray, idx: np.ndarray, Q: np.ndarray, P: np.ndarray,
                       reference: tuple[np.ndarray, np.ndarray] | None = None,
                       all_or_nothing: np.ndarray | None = None) -> np.ndarray:
    """(n, 3): surface X (n, 3) metres, F (m, 3), with vertices idx (k,) moved onto their
    scan points Q (k, 3), each as far as it goes without turning a triangle further than
    PROJECT_TURN from X or folding it against the template P (n, 3): a vertex whose move
    turns one of its triangles goes half as far, again while it does (PROJECT_HALVINGS),
    then stays (taking it back is not checked again: the caller's blend sees to what that
    turns). A sliver beside a vertex so costs it part of its way, not all of it. Triangles
    folded against P before the step are nobody's fault and are left as they are.
    all_or_nothing (n,) bool: vertices that go all the way or stay, and whose triangles'
    folds against the template are left to the caller (thin folds over the mouth and the
    eyes, which the caller blends back whole with the rings around them: moved part way,
    the lips' rims crease as they play). reference: fold_reference(P, F), if the caller has it."""
    reference = fold_reference(P, F) if reference is None else reference
    whole_way = np.zeros(len(X), dtype=bool) if all_or_nothing is None else np.asarray(all_or_nothing, dtype=bool)
    # triangles this step keeps from folding against the template: not the thin folds', nor
    # any folded before it (the stages' blends may leave one: no move of its corners is to blame)
    others = ~whole_way[F].any(axis=1) & ~folded_triangles(P, X, F, reference=reference)
    step = np.ones(len(idx))  # the share of the way to Q
    Y = np.array(X, dtype=np.float64)
    for halving in range(PROJECT_HALVINGS + PROJECT_REVERTS):
        Y[idx] = X[idx] + step[:, None] * (Q - X[idx])
        bad = folded_triangles(X, Y, F, PROJECT_TURN) | (folded_triangles(P, Y, F, reference=reference) & others)
        if not bad.any():
            return Y
        turning = np.zeros(len(X), dtype=bool)
        turning[F[bad].ravel()] = True
        step[turning[idx]] *= 0.5 if halving < PROJECT_HALVINGS else 0.0
        step[turning[idx] & whole_way[idx]] = 0.0
    Y[idx] = X[idx] + step[:, None] * (Q - X[idx])
    return Y


def harmonic_displacement(L: sp.csr_matrix, D: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(n, 3): D (n, 3) where `known` (n,) bool, and elsewhere the harmonic extension of it
    over the graph Laplacian L (n, n): L D = 0 on the unknown rows (each unknown point the
    mean of its neighbours), so a region without data follows its rim smoothly."""
    known = np.asarray(known, dtype=bool)
    u = np.flatnonzero(~known)
    k = np.flatnonzero(known)
    out = np.asarray(D, dtype=np.float64).copy()
    if len(u) == 0 or len(k) == 0:
        return out
    L = sp.csr_matrix(L)
    A = L[u][:, u].tocsc()
    rhs = -(L[u][:, k] @ out[k])
    out[u] = symmetric_splu(A).solve(np.asarray(rhs))
    return out


def whole(P: np.ndarray, X_safe: np.ndarray, X: np.ndarray, F: np.ndarray, ring: sp.csr_matrix,
          edges: np.ndarray, query: MeshQuery, rounds: int = 6,
          reference: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, int, int]:
    """X (n, 3) blended back towards X_safe (n, 3), which neither folds against P nor cuts
    through itself, wherever X does either: folds (blend_away_folds) and crossings
    (fae.adapt.untangle) in turn, since each blend can undo the other's work. Returns X
    and how many vertices each kind of blend touched. reference: fold_reference(P, F)."""
    blended = untangled = 0
    for _ in range(rounds):
        X, b = blend_away_folds(P, X_safe, X, F, ring, reference=reference)
        X, weight = untangle(F, X, X_safe, edges=edges, query=query)
        blended, untangled = blended + b, untangled + int(np.sum(weight < 1.0))
        if not folded_triangles(P, X, F, reference=reference).any():
            break
    return X, blended, untangled


def fit_to_scan(P: np.ndarray, F: np.ndarray, scan: Surface, movable: np.ndarray,
                landmarks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                head: np.ndarray | None = None, stiffness: np.ndarray | None = None,
                detail: np.ndarray | None = None, rays: np.ndarray | None = None,
                start: np.ndarray | None = None, placed: np.ndarray | None = None,
                carry: Callable[[np.ndarray], np.ndarray] | None = None,
                fill: np.ndarray | None = None) -> SurfaceFit:
    """Fit the template skin P (n, 3) metres, F (m, 3) to `scan` (face frame, head part only).

    movable (n,) bool: skin a scanner can see (the rest follows its neighbours); landmarks:
    (faces (k,), bary (k, 3), points (k, 3) metres) feature points on the skin and where
    they are on the scan; head (n,) bool: skin used for the affine start (default movable);
    stiffness (n,): a multiplier of the smoothness per vertex (thin, creased parts such as
    eyelids and ears bend less than a cheek; default 1); detail (n,) bool: skin that
    follows the scan's detail (stages softer than DETAIL_STIFFNESS and the projection);
    the rest (thin folds such as eyelids and ears, a neck the scan cuts short) keeps the
    shape the stiff stages gave it (default: all movable skin); rays (n,) bool: skin that
    may take the scan along its normal where its closest point faces away (scan_pairs;
    default all); the rest, thin folds over the mouth and the eyes, goes onto the scan
    all the way or not at all in the projection (projected_part_way); start (k,): the
    weight of each feature point in the affine start (default 1 each; 0 leaves it out);
    placed (n,) bool: skin that its feature points place in the stiff stages, with no
    pull of the scan until the detail stages (an ear found centimetres from the
    template's: the scan closest to it is scalp, not ear); carry(X) -> X (n, 3) metres,
    template vertex order: the skin after the start with parts found on the scan carried
    there (the ears: fae.adapt.ears.ears_carried), since the stiff stages do not move a part
    centimetres apart from the rest; blended back wherever that folds the skin or cuts
    through itself. fill (n,) bool: skin the scan's own points pull too in the detail
    stages (scan_pulls; default none): where the scan has shape the template lacks.
    """
    t0 = time.perf_counter()
    P_in = np.asarray(P, dtype=np.float64)
    F_in = np.asarray(F, dtype=np.int64)
    # the template's seams (coincident vertices) are welded: the halves must move as one
    n, label = coincident_groups(P_in)
    P = group_means(P_in, label, n)
    F = label[F_in]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 2] != F[:, 0])]
    movable = np.bincount(label, weights=np.asarray(movable, dtype=float), minlength=n) > 0
    if rays is not None:
        rays = np.bincount(label, weights=np.asarray(rays, dtype=float), minlength=n) > 0
    head = None if head is None else np.bincount(label, weights=np.asarray(head, dtype=float), minlength=n) > 0
    detail = movable if detail is None else movable & (
        np.bincount(label, weights=np.asarray(detail, dtype=float), minlength=n) > 0)
    if placed is not None:
        placed = np.bincount(label, weights=np.asarray(placed, dtype=float), minlength=n) > 0
    if fill is not None:
        fill = np.bincount(label, weights=np.asarray(fill, dtype=float), minlength=n) > 0
    if landmarks is not None:
        lm_corners = label[F_in[landmarks[0]]]  # (k, 3) welded corners of each feature point's triangle
    fixed = None
    if start is not None and (landmarks is None or len(start) != len(landmarks[0])):
        raise ValueError(f"fit_to_scan: {len(start)} start weights for "
                         f"{0 if landmarks is None else len(landmarks[0])} feature points")
    if landmarks is not None and len(landmarks[0]):
        share = np.ones(len(landmarks[0])) if start is None else np.asarray(start, dtype=np.float64)
        use = share > 0
        fixed = (np.einsum("kj,kjd->kd", landmarks[1][use], P[lm_corners[use]]), landmarks[2][use], share[use])
    L = graph_laplacian(F, n, P, NEIGHBOUR_RADIUS)
    L_graph = L
    if stiffness is not None:
        per = np.bincount(label, weights=np.asarray(stiffness, dtype=float), minlength=n) / np.bincount(label, minlength=n)
        L = sp.diags(per) @ L
    LtL = (L.T @ L).tocsc()
    if landmarks is not None and len(landmarks[0]):
        fl, bl, ql = landmarks
        rows = np.repeat(np.arange(len(fl)), 3)
        B = sp.csr_matrix((bl.ravel(), (rows, lm_corners.ravel())), shape=(len(fl), n))
        BtB = LANDMARK_WEIGHT * (B.T @ B)
    else:
        B = None

    def stage_matched(a: float) -> np.ndarray:
        matched = movable if a >= DETAIL_STIFFNESS else detail
        if placed is not None and a >= DETAIL_STIFFNESS:
            matched = matched & ~placed
        return matched

    def stage_factors(a: float, rows: np.ndarray) -> list:
        """[SuperLU factors] of a stage's matrix; rows (n,) bool: vertices with a data row. In
        a list that the factoring thread empties when the stage is done: SciPy's SuperLU
        frees its memory only in the thread that made it (scipy#15921; let go on the main
        thread, every fit left 1.9 GB of address space and about 170 MB behind)."""
        M = a * a * LtL + sp.diags(rows.astype(np.float64))
        if B is not None:
            M = M + (a / STIFFNESS[0]) ** LANDMARK_FADE * BtB
        return [symmetric_splu(M)]

    stages = []
    reaches = np.geomspace(REACH[0], REACH[1], len(STIFFNESS))
    # every movable vertex has a data row (weight 1) in every round, so a stage factors its
    # matrix once; a vertex without a compatible scan point this round is asked to stay
    blended_total = 0
    quiet = np.zeros(n, dtype=bool)  # skin whose scan pull folded it: it follows its neighbours
    # the factoring runs on a thread of its own, a stage ahead (SuperLU lets go of the GIL for
    # most of its work): the first stage's during the start, each next stage's during this
    # stage's later rounds. So skin let go in a stage's first round leaves the next stage's
    # matrix, and skin let go later the matrix of the stage after (it stays put until then:
    # the busts' errors within 0.003 % of the diagonal of factoring each stage at its start,
    # the fit 15-25 % faster, no longer waiting for its factors)
    with ThreadPoolExecutor(1) as factoring:
        ahead = factoring.submit(stage_factors, STIFFNESS[0], stage_matched(STIFFNESS[0]))
        A, partial = affine_to_scan(P, scan, movable if head is None else head, points=fixed, similarity=SIMILARITY_START)
        edge_reach = PARTIAL_EDGE_REACH if partial else EDGE_REACH
        X = apply_transform(A, P)
        ring = adjacency_matrix(F, n)
        fold_ref = fold_reference(P, F)  # every round tests its step against the template
        edges = mesh_edges(F)
        query = MeshQuery(X, F)
        if carry is not None:  # neither folding nor cutting through itself, as every stage
            X = whole(P, X, group_means(np.asarray(carry(X[label]), dtype=np.float64), label, n), F, ring, edges,
                      query, reference=fold_ref)[0]
        X_whole = X
        for stage, (a, reach) in enumerate(zip(STIFFNESS, reaches)):
            matched = stage_matched(a)
            fade = (a / STIFFNESS[0]) ** LANDMARK_FADE  # feature points place the parts; the scan gives the detail
            factors = ahead
            solve = None
            for round_ in range(ROUNDS):
                NX = per_vertex_normals(X, F)
                idx_all, Q_all = scan_pairs(X, NX, scan, reach, matched, along_normal=True, rays=rays,
                                            edge_reach=edge_reach)
                if solve is None:
                    solve = factors.result()[0].solve
                keep = ~quiet[idx_all]
                idx, Q = idx_all[keep], Q_all[keep]
                rhs = np.zeros((n, 3))
                rhs[idx] = Q - X[idx]
                if fill is not None and a < DETAIL_STIFFNESS:
                    acc, wsum = scan_pulls(X, NX, F, query, scan, reach, fill & matched & ~quiet, edge_reach)
                    rhs = (rhs + FILL_WEIGHT * acc) / (1.0 + FILL_WEIGHT * wsum[:, None])
                if B is not None:
                    rhs += fade * LANDMARK_WEIGHT * (B.T @ (landmarks[2] - B @ X))
                X_next = X + solve(rhs)
                bad = folded_triangles(P, X_next, F, reference=fold_ref)
                if bad.any():
                    # the scan's pull that folds a place is let go there (from a later stage on, the
                    # place moves smoothly with its neighbours instead of being blended back again)
                    zone = np.zeros(n, dtype=bool)
                    zone[F[bad].ravel()] = True
                    for _ring in range(QUIET_RINGS):
                        zone |= (ring @ zone.astype(np.float64)) > 0
                    quiet |= zone
                X, blended = blend_away_folds(P, X, X_next, F, ring, reference=fold_ref)  # what still folds: blended back
                blended_total += blended
                if round_ == 0 and stage + 1 < len(STIFFNESS):
                    a_next = STIFFNESS[stage + 1]
                    ahead = factoring.submit(stage_factors, a_next, stage_matched(a_next) & ~quiet)
            solve = None  # the factors are let go in the thread that made them
            factoring.submit(factors.result().clear)
            rms = float(np.sqrt(np.mean(np.sum((X[idx] - Q) ** 2, axis=1)))) if len(idx) else np.inf
            # nor may a stage cut through itself (an ear pressed into the scalp, the mouth's lining
            # through a lip): blended back to the last stage wherever it does
            X, _, untangled = whole(P, X_whole, X, F, ring, edges, query, reference=fold_ref)
            X_whole = X
            stages.append({"stiffness": a, "reach_m": float(reach), "pairs": int(len(idx)), "pair_rms_m": rms,
                           "folded": int(folded_triangles(P, X, F, reference=fold_ref).sum()), "quiet_vertices": int(quiet.sum()),
                           "blended_vertices": blended_total,
                           "untangled_vertices": untangled, "seconds": time.perf_counter() - t0})
    # skin the scan does not reach (a neck below its cut, a crown above a face scan) takes
    # the harmonic extension of the displacement around it: what the stages left there is
    # the blends' patchwork
    on_scan = np.zeros(n, dtype=bool)
    on_scan[idx] = True
    far = np.zeros(n, dtype=bool)  # skin near what the scan reaches keeps its fit
    if on_scan.any():
        far[~on_scan] = cKDTree(P[on_scan]).query(P[~on_scan])[0] > EXTEND_START
    # (of the displacement from the start: the graph Laplacian's weights do not reproduce a
    # linear field, and a face scan's turn and scale carried to the back of the head by them
    # swung the neck forward; the blend that undid that left ridges on the crown)
    X_start = apply_transform(A, P)
    X_ext = X_start + harmonic_displacement(L_graph, X - X_start, ~far)
    X_ext, ext_blended, ext_untangled = whole(P, X_whole, X_ext, F, ring, edges, query, reference=fold_ref)
    extended = not folded_triangles(P, X_ext, F, reference=fold_ref).any()
    if extended:
        X = X_whole = X_ext
    # paper 001's local step: onto the scan where it is close, never folding a triangle
    NX = per_vertex_normals(X, F)
    idx, Q = scan_pairs(X, NX, scan, PROJECT_REACH, detail, rays=rays, edge_reach=edge_reach)
    Y = projected_part_way(X, F, idx, Q, P, reference=fold_ref, all_or_nothing=None if rays is None else ~rays)
    # the projection neither folds nor cuts through itself: blended back to the last stage
    # (which does neither) where it would; each blend can undo the other's work, so in turn
    Y, blended, untangled = whole(P, X_whole, Y, F, ring, edges, query, reference=fold_ref)
    stages.append({"extended_to": int((~on_scan).sum()) if extended else 0,
                   "extension_blended": ext_blended, "extension_untangled": ext_untangled, "projected": int(len(idx)),
                   "blended_vertices": blended, "untangled_vertices": untangled,
                   "seconds": time.perf_counter() - t0})
    Y = Y[label]
    folded = int(folded_triangles(P_in, Y, F_in).sum())
    return SurfaceFit(Y, A, partial, stages, folded)
