"""The head in a real scan: its pose, scale and the part of the scan the template models.

    find_head(template, scan_V, scan_F) -> HeadInScan

A user's scan arrives in any unit and orientation, with a plinth, shoulders, chest, hair,
holes and stray pieces. The template models a head and the top of a neck; nothing below
may pull its skin.

1. Pose and scale (head_pose): the template's head (its visible skin above the chin,
   cranium, face and ears) is placed onto the scan by trimmed similarity ICP from many
   starts: the template's up along each of the scan's axes and principal axes (both
   signs), turned about it in 45-degree steps, sized to three shares of the scan's extent
   along that up and set at its top, refined by a few steps of symmetric trimmed ICP
   (_icp). Each start is scored in the template's frame by trimmed mean distances:
   template head -> scan (the head must lie on the scan), scan -> template head for the
   scan inside the template head's box (the scan there must be head: a template shrunk
   into a corner of a plinth or a shoulder leaves scan unexplained), and FACE_WEIGHT x
   template face -> scan (the face tells front from back). The template moves, not the
   scan, so the shoulders below the box count for nothing. The best starts are refined
   with every point, and the winner's last turn is decided by the face alone (a head
   turned on its neck, hair or a wreath must not).
2. The head part (head_part): in the face frame at the template's size, scan vertices
   within the template head's box (5 cm around it; below the chin no wider than the box)
   and above the template's neck end; from CHIN_MARGIN below the chin down, only neck:
   within NECK_RADIUS_SHARE of the template neck's radius from its axis, and facing
   sideways unless within the neck's own radius (the top of a chest or shoulder faces
   up; a throat may face any way); then only the connected piece (welded where texture
   seams split the scan) that holds the face. The report names its vertex count and
   bounds.
   A scan whose pose this does not trust (a face without the rest of the head) is
   searched again with the template's face alone. A scan in pieces far apart
   (scan_clusters: a stray object metres away, two busts side by side) has each of its
   largest searched alone as well, and the best head found is taken, their count
   reported.
3. Confidence: the share of the template's face that the scan covers within
   FACE_NEAR metres after the rigid fit, and the trimmed residual over the face. Below
   MIN_FACE_COVERAGE, or above MAX_HEAD_RESIDUAL, the pose is not to be trusted and
   fae adapt stops with exit status 2 (see fae.commands.adapt).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from fae.adapt.calibration import scan_unit, similarity_icp, similarity_transform
from fae.cores import workers
from fae.linalg import axis_angle, turn_between
from fae.mesh import coincident_groups
from fae.anatomy.surface_points import markup_positions
from fae.io.facemodel import FaceModel

SCAN_SAMPLES = 10000  # scan vertices (at most) used by the pose search
REFINED_STARTS = 4  # the best starts refined with every point
# every start takes SCREEN_ITERATIONS coarse ICP steps; the best SCREEN_KEEP share of them
# (at least SCREEN_MIN) take the rest of COARSE_ITERATIONS: a start two steps in that ranks
# in the last five sixths does not end first (the three busts, the suite's turned scans)
COARSE_ITERATIONS, SCREEN_ITERATIONS = 5, 2
SCREEN_KEEP, SCREEN_MIN = 1.0 / 6.0, 12
COARSE_SCAN, COARSE_HEAD = 3000, 400  # points (about) of scan and template that score the starts
YAW_STEPS = 8  # starts turned about each up direction (45 degrees apart)
HEAD_SHARES = (0.1, 0.2, 0.35, 0.6, 0.95)  # starting head height (chin to crown) / scan extent along up (0.1, 0.2: a bust on a column)
KEEP = 0.85  # trimmed ICP: share of pairs kept
FACE_WEIGHT = 2.0  # of the face's distance in a start's score
CHIN_MARGIN = 0.03  # m: the neck rule starts this far below the chin
NECK_RADIUS_SHARE = 1.3  # below the chin, scan within this many template neck radii of its axis
NECK_MAX_UPWARD = 0.5  # ... whose normal is within 60 degrees of horizontal
FACE_NEAR = 0.008  # m: a face sample is covered when the scan is this close after the rigid fit
MIN_FACE_COVERAGE = 0.6  # below this share of the face covered, the pose is not trusted
UNIT_SNAP = 1.3  # a fitted scale within this factor of a length unit is taken as that unit
MAX_HEAD_RESIDUAL = 0.012  # m: trimmed mean template head -> scan distance beyond which it is not
CLUSTER_GAP_SHARE = 0.1  # of the largest piece's diagonal: pieces farther apart are searched apart
MAX_CLUSTERS = 4  # the largest clusters searched alone
MIN_CLUSTER_VERTICES = 100
# a placement from feature points and the search's are one head within these: not turned
# over, not another head beside it (the marble bust's midline points: 25 degrees, 1.36x and
# 0.07 m apart, its 72 points 8 degrees, 1.05x and 0.03 m: the points place the template's
# markup, the search its whole head; the fit from the search's placement came out closer)
POSE_AGREE_TURN = 45.0  # degrees
POSE_AGREE_SCALE = 1.5  # either way
POSE_AGREE_SHIFT = 0.1  # metres between their face frames' origins


@dataclass
class HeadInScan:
    """Where the template's head lies in a scan.

    transform   (4, 4) scan frame and unit -> the template's face frame (metres)
    unit        the scan's length unit ("mm", "m", ...; "unknown" when none fits the scale)
    keep        (n,) bool over the scan's vertices: the head part (the rest is ignored)
    face_coverage  share of the template face's samples with scan within FACE_NEAR metres
    residual    trimmed mean distance, template face -> scan, metres, after the rigid fit
    scale       scan units -> metres as fitted (before snapping to a unit)
    template_to_scan  (4, 4) the similarity found, the template's face frame -> the scan's
    heads       how many of the scan's clusters (pieces far apart) held a head found (1 when
                the scan is one cluster)
    """

    transform: np.ndarray
    unit: str
    keep: np.ndarray
    face_coverage: float
    residual: float
    scale: float
    template_to_scan: np.ndarray
    heads: int = 1

    @property
    def trusted(self) -> bool:
        return self.face_coverage >= MIN_FACE_COVERAGE and self.residual <= MAX_HEAD_RESIDUAL

    def report(self, scan_V: np.ndarray) -> dict:
        """JSON-ready description of the head part (in the scan's own frame and unit)."""
        part = np.asarray(scan_V)[self.keep]
        return {"scan_vertices": int(len(self.keep)), "head_vertices": int(self.keep.sum()),
                "head_bounds_min": part.min(axis=0).tolist() if len(part) else None,
                "head_bounds_max": part.max(axis=0).tolist() if len(part) else None,
                "scan_unit": self.unit, "face_coverage": self.face_coverage,
                "pose_residual_m": self.residual, "trusted": self.trusted, "heads_found": self.heads}


@dataclass
class TemplateHead:
    """The template's parts the search needs, in its face frame (metres).

    head        (k, 3) samples of the visible skin above the chin (cranium, face, ears)
    face        (f, 3) samples of the front of the face (brow to chin, in front of the ears)
    box_min, box_max  (3,) the head samples' bounds, a little enlarged
    chin_y      height of the chin (2.1)
    neck_bottom height where the template's neck ends
    neck_axis   (2,) x, z of the neck's axis; neck_radius its mean radius
    """

    head: np.ndarray
    face: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    chin_y: float
    neck_bottom: float
    neck_axis: np.ndarray
    neck_radius: float


def template_head(template: FaceModel) -> TemplateHead:
    """The template's head, face and neck measurements (see TemplateHead)."""
    from fae.adapt.correspondence import grid_sample
    from fae.adapt.transfer import visible_skin

    V = np.asarray(template.skin_vertices, dtype=np.float64)
    seen = visible_skin(template)
    fdp = markup_positions(template)
    chin_y = float(fdp["2.1"][1]) if "2.1" in fdp else float(V[:, 1].min() + 0.3 * np.ptp(V[:, 1]))
    head_mask = seen & (V[:, 1] >= chin_y - 0.005)
    spacing = max(float(np.ptp(V[head_mask], axis=0).max()) / 40.0, 1e-4)
    head = V[grid_sample(V, spacing, head_mask)]
    front_z = min(fdp[n][2] for n in ("10.9", "10.10")) if "10.9" in fdp and "10.10" in fdp else np.median(V[:, 2])
    top_face = fdp["11.1"][1] if "11.1" in fdp else V[:, 1].max()
    face_mask = seen & (V[:, 1] >= chin_y - 0.003) & (V[:, 1] <= top_face) & (V[:, 2] >= front_z)
    face = V[grid_sample(V, spacing / 2, face_mask)]
    names = list(template.region_names)
    if "neck" in names:
        neck = V[(np.asarray(template.skin_region) == names.index("neck")) & (V[:, 1] < chin_y)]
    else:
        neck = V[V[:, 1] < chin_y]
    neck_bottom = float(V[:, 1].min())
    low = neck[neck[:, 1] < 0.5 * (chin_y + neck_bottom)] if len(neck) else V[V[:, 1] < chin_y]
    axis = 0.5 * (low[:, [0, 2]].min(axis=0) + low[:, [0, 2]].max(axis=0))
    radius = float(np.mean(np.linalg.norm(low[:, [0, 2]] - axis, axis=1)))
    pad = 0.1 * np.ptp(head, axis=0)
    return TemplateHead(head=head, face=face, box_min=head.min(axis=0) - pad, box_max=head.max(axis=0) + pad,
                        chin_y=chin_y, neck_bottom=neck_bottom, neck_axis=axis, neck_radius=radius)


def _up_candidates(S: np.ndarray) -> list[np.ndarray]:
    """Unit directions the head's up may take in the scan: its axes and principal axes,
    both signs, without near-duplicates (within 15 degrees)."""
    c = S.mean(axis=0)
    _, _, Vt = np.linalg.svd(S - c, full_matrices=False)
    out: list[np.ndarray] = []
    for d in itertools.chain(np.eye(3), Vt):
        for sign in (1.0, -1.0):
            u = sign * d / np.linalg.norm(d)
            if all(np.dot(u, w) < np.cos(np.radians(15.0)) for w in out):
                out.append(u)
    return out


def _icp(head: TemplateHead, A: np.ndarray, S: np.ndarray, tree: cKDTree, s: float, R: np.ndarray,
         t: np.ndarray, iterations: int, workers: int = 1) -> tuple[float, np.ndarray, np.ndarray]:
    """Trimmed symmetric similarity ICP: x -> s R x + t taking template head points A (n, 3)
    onto the scan cloud S (tree over S). Pairs go both ways: each template point to its
    closest scan point, and each scan point inside the template head's box to its closest
    template point; so the template can neither swell around the scan (the scan inside it
    pulls it in) nor shrink into a corner of it."""
    treeA = cKDTree(A)
    for _ in range(iterations):
        Y = s * A @ R.T + t
        d1, j1 = tree.query(Y, workers=workers)
        good1 = d1 <= np.quantile(d1, KEEP)
        X = (S - t) @ R / s
        inbox = np.flatnonzero(np.all((X >= head.box_min) & (X <= head.box_max), axis=1))
        inbox = inbox[:: max(1, len(inbox) // (2 * len(A)))]  # at most twice as many scan pairs as template ones
        src, dst = [A[good1]], [S[j1[good1]]]
        if len(inbox) > 10:
            d2, j2 = treeA.query(X[inbox], workers=workers)
            d2 = d2 * s
            good2 = d2 <= np.quantile(d2, KEEP)
            src.append(A[j2[good2]])
            dst.append(S[inbox[good2]])
        s, R, t = similarity_transform(np.vstack(src), np.vstack(dst))
        if not (np.isfinite(s) and s > 0.0):  # every pair on one scan vertex (a start in a hole): no pose
            break
    return s, R, t


def _trimmed_mean(d: np.ndarray, keep: float = KEEP) -> float:
    if len(d) == 0:
        return np.inf
    d = np.sort(d)[: max(1, int(keep * len(d)))]
    return float(np.mean(d))


def head_pose(head: TemplateHead, scan_V: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, float]:
    """x -> s R x + t taking the template's face frame into the scan's frame (so the
    inverse takes the scan into the face frame), and the start's score (metres of the
    template frame; lower is better). See the module docstring."""
    V = np.asarray(scan_V, dtype=np.float64)
    S = V[:: max(1, len(V) // SCAN_SAMPLES)]
    tree = cKDTree(S)
    A = head.head
    top = A[np.argmax(A[:, 1])]
    centre = A.mean(axis=0)
    height = float(A[:, 1].max() - head.chin_y)
    probe = A[:: max(1, len(A) // 400)]
    face_probe = head.face[:: max(1, len(head.face) // 400)]
    A = np.vstack([A, head.face])  # the face counts twice: it tells front from back
    head_tree = cKDTree(head.head)

    def score(s, R, t, cloud=S, cloud_tree=tree) -> float:
        # in the template's frame: template head -> scan, and scan in the head's box -> head
        if not (np.isfinite(s) and s > 0.0):  # a start in a hole paired every point with one vertex
            return np.inf
        d1 = cloud_tree.query(s * probe @ R.T + t)[0] / s
        d3 = cloud_tree.query(s * face_probe @ R.T + t)[0] / s
        X = (cloud - t) @ R / s
        inbox = np.all((X >= head.box_min) & (X <= head.box_max), axis=1)
        d2 = head_tree.query(X[inbox])[0] if inbox.sum() > 10 else np.full(1, np.inf)
        e = _trimmed_mean(d1) + _trimmed_mean(d2) + FACE_WEIGHT * _trimmed_mean(d3, 0.95)
        return e if np.isfinite(e) else np.inf  # sorted() cannot order a NaN: it would crowd out the best

    starts = []
    for up in _up_candidates(S):
        along = S @ up
        extent = float(np.ptp(along))
        if extent <= 1e-9 * max(float(np.ptp(S, axis=0).max()), 1e-300):
            continue  # a flat scan has no extent along its normal
        R_up = turn_between(np.array([0.0, 1.0, 0.0]), up)
        top_point = S[np.argmax(along)]
        high = S[along >= along.max() - 0.3 * extent]
        for share in HEAD_SHARES:
            s = share * extent / height
            for k in range(YAW_STEPS):
                R = axis_angle(up, 2 * np.pi * k / YAW_STEPS) @ R_up
                # the template's crown at the scan's top, its centre over the top part's centre
                t = top_point - s * R @ top
                delta = high.mean(axis=0) - (s * R @ centre + t)
                t = t + delta - up * np.dot(delta, up)  # across up only: the crown stays at the top
                starts.append((s, R, t))
    coarse = S[:: max(1, len(S) // COARSE_SCAN)]  # the many starts are told apart coarsely
    coarse_tree = cKDTree(coarse)
    coarse_A = A[:: max(1, len(A) // COARSE_HEAD)]

    def coarse_fit(start, iterations):
        s, R, t = _icp(head, coarse_A, coarse, coarse_tree, *start, iterations=iterations)
        return score(s, R, t, coarse, coarse_tree), s, R, t

    def fine_fit(start):
        s, R, t = _icp(head, A, S, tree, *start[1:], iterations=20)
        return score(s, R, t), s, R, t

    # the starts are independent: on every core (the tree queries and numpy release the GIL)
    with ThreadPoolExecutor(workers(4)) as pool:
        screened = sorted(pool.map(lambda x: coarse_fit(x, SCREEN_ITERATIONS), starts), key=lambda x: x[0])
        kept = screened[: max(SCREEN_MIN, int(np.ceil(SCREEN_KEEP * len(screened))))]
        scored = sorted(pool.map(lambda x: coarse_fit(x[1:], COARSE_ITERATIONS - SCREEN_ITERATIONS), kept),
                        key=lambda x: x[0])
        refined = list(pool.map(fine_fit, scored[:REFINED_STARTS]))
    best = (np.inf, 1.0, np.eye(3), np.zeros(3))  # (no start, or none scored: the identity)
    for fit in refined:
        if fit[0] < best[0]:
            best = fit
    e, s, R, t = best
    # the face decides the last turn: a head turned on its neck, hair or a wreath must not
    s, R, t, _ = similarity_icp(head.face, tree, S, s, R, t, iterations=20, keep=0.8)
    return s, R, t, e


def head_part(head: TemplateHead, X: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(n,) bool: scan vertices X (n, 3), already in the face frame (metres), that belong to
    the head and neck the template models (see the module docstring); F (m, 3) the scan's
    faces, for its connected pieces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    X = np.asarray(X, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    radial = np.linalg.norm(X[:, [0, 2]] - head.neck_axis, axis=1)
    keep = X[:, 1] >= head.neck_bottom
    neck_like = radial <= NECK_RADIUS_SHARE * head.neck_radius
    if len(F):  # a neck's surface faces sideways; the top of a chest or shoulder faces up
        from fae.adapt.geometry import per_vertex_normals

        # (within the template neck's own radius it is neck, whichever way it faces: a throat)
        neck_like &= (radial <= head.neck_radius) | (np.abs(per_vertex_normals(X, F)[:, 1]) <= NECK_MAX_UPWARD)
    keep &= (X[:, 1] >= head.chin_y - CHIN_MARGIN) | neck_like
    keep &= np.all(X[:, [0, 2]] >= head.box_min[[0, 2]] - 0.05, axis=1)
    keep &= np.all(X[:, [0, 2]] <= head.box_max[[0, 2]] + 0.05, axis=1)
    keep &= X[:, 1] <= head.box_max[1] + 0.05
    # below the chin, nothing wider than the head itself (a cloak or shoulders rising to the jaw)
    below = X[:, 1] < head.chin_y
    keep[below] &= np.all((X[below][:, [0, 2]] >= head.box_min[[0, 2]]) & (X[below][:, [0, 2]] <= head.box_max[[0, 2]]),
                          axis=1)
    if len(F) == 0 or not keep.any():
        return keep
    # texture seams split a scan's vertices: pieces are found on welded positions
    _, weld = coincident_groups(X)
    both = keep[F].all(axis=1)
    G = weld[F[both]]
    n = len(X)
    graph = coo_matrix((np.ones(2 * len(G)), (np.r_[G[:, 0], G[:, 1]], np.r_[G[:, 1], G[:, 2]])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    # the piece that holds the face: the one nearest the template's face samples
    near = cKDTree(X[keep]).query(head.face)[1]
    face_labels = label[weld[np.flatnonzero(keep)[near]]]
    main = np.bincount(face_labels).argmax()
    return keep & (label[weld] == main)


def kept_part(V: np.ndarray, F: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh V (n, 3), F (m, 3) cut to the vertices `keep` (n,) bool: (V' (k, 3), F' (m', 3)),
    the faces whose corners are all kept, renumbered, with vertices at the same position
    welded into one (texture seams split a scan's vertices: unwelded, every seam would be
    an edge of the surface, and the normals along it half-fans)."""
    keep = np.asarray(keep, dtype=bool)
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    faces = F[keep[F].all(axis=1)]
    k, weld = coincident_groups(V)
    first = np.zeros(k, dtype=np.int64)
    first[weld[::-1]] = np.arange(len(V))[::-1]  # the lowest index in each group
    faces = first[weld][faces]  # each corner to the first vertex at its position
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    used = np.zeros(len(V), dtype=bool)
    used[faces.ravel()] = True
    new = np.full(len(V), -1, dtype=np.int64)
    new[used] = np.arange(int(used.sum()))
    return np.asarray(V)[used], new[faces]


def find_head(template: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray) -> HeadInScan:
    """The template's head found in a scan in any frame and unit (see the module docstring)."""
    V = np.asarray(scan_V, dtype=np.float64)
    if len(V) < 100:
        raise ValueError(f"the scan has {len(V)} vertices: too few to find a head in")
    head = template_head(template)
    found = _searched(head, V, scan_F)
    # pieces far apart (a stray object metres off, two busts side by side: the search over
    # the whole scan may trust a pose between them) are searched alone
    F = np.asarray(scan_F, dtype=np.int64).reshape(-1, 3)
    clusters = [c for c in scan_clusters(V, F) if len(c) >= MIN_CLUSTER_VERTICES][:MAX_CLUSTERS]
    if len(clusters) < 2:
        return found
    heads = []
    for idx in clusters:
        inside = np.zeros(len(V), dtype=bool)
        inside[idx] = True
        renumber = np.cumsum(inside) - 1
        alone = _searched(head, V[idx], renumber[F[inside[F].all(axis=1)]])
        if alone.trusted:
            keep = np.zeros(len(V), dtype=bool)
            keep[idx[alone.keep]] = True
            heads.append(replace(alone, keep=keep))
    if not heads:
        return found
    best = min(heads, key=lambda h: h.residual)
    return replace(best, heads=len(heads))


def _turned_over(head: TemplateHead, V: np.ndarray, scan_F: np.ndarray, found: HeadInScan) -> HeadInScan:
    """The head `found` in V (n, 3), F (m, 3) turned upside down about the face's forward
    axis through its middle, then fitted by the face alone (similarity ICP): the other pose
    a face scan leaves open (see other_poses)."""
    s, R, t = _similarity_of(found.template_to_scan)
    centre = head.face.mean(axis=0)
    R0 = R @ np.diag([-1.0, -1.0, 1.0])  # half a turn about the face frame's +z
    t0 = s * R @ centre + t - s * R0 @ centre
    S = V[:: max(1, len(V) // SCAN_SAMPLES)]
    s, R, t, _ = similarity_icp(head.face, cKDTree(S), S, s, R0, t0, iterations=30, keep=0.8)
    return _head_in_scan(head, V, scan_F, s, R, t)


def _searched(head: TemplateHead, V: np.ndarray, F: np.ndarray) -> HeadInScan:
    """The head found in V (n, 3), F (m, 3) by head_pose, and again with the template's face
    alone when that is not trusted (a face without the rest of the head: a face scan, a mask)."""
    s, R, t, _ = head_pose(head, V)
    found = _head_in_scan(head, V, F, s, R, t)
    if not found.trusted:
        second = _face_searched(head, V, F)
        if second.residual < found.residual:
            found = second
    return found


def _face_searched(head: TemplateHead, V: np.ndarray, F: np.ndarray) -> HeadInScan:
    """The head found in V (n, 3), F (m, 3) by head_pose with the template's face alone."""
    pad = 0.1 * np.ptp(head.face, axis=0)
    face_only = replace(head, head=head.face, box_min=head.face.min(axis=0) - pad, box_max=head.face.max(axis=0) + pad)
    s, R, t, _ = head_pose(face_only, V)
    return _head_in_scan(head, V, F, s, R, t)


def other_poses(template: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray, found: HeadInScan) -> Iterator[HeadInScan]:
    """Other trusted poses of the head in a scan, for when the face-landmark model finds no
    face on the render of the pose `found`: a face scan leaves up and down open, and a
    bearded face cut to a mask matched the template's face upside down (brow on beard, 70 %
    of the face covered: trusted). In turn: the pose found by the face alone, and `found`
    turned over (_turned_over)."""
    V = np.asarray(scan_V, dtype=np.float64)
    head = template_head(template)
    for make in (lambda: _face_searched(head, V, scan_F), lambda: _turned_over(head, V, scan_F, found)):
        other = make()
        if other.trusted:
            yield other


def scan_clusters(V: np.ndarray, F: np.ndarray, gap_share: float = CLUSTER_GAP_SHARE) -> list[np.ndarray]:
    """Vertex indices (k_i,) of each cluster of the scan V (n, 3), F (m, 3), most vertices
    first: space is cut into cubes of gap_share x the diagonal of the largest connected
    piece (welded where texture seams split it), and cubes that hold vertices and touch
    (corners included) are one cluster. So pieces closer than about a cube are together
    (a bust's separate wreath, its plinth), farther ones apart."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    _, weld = coincident_groups(V)
    n = len(V)
    G = weld[F]
    graph = coo_matrix((np.ones(2 * len(G)), (np.r_[G[:, 0], G[:, 1]], np.r_[G[:, 1], G[:, 2]])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    piece = label[weld]
    lo = np.full((piece.max() + 1, 3), np.inf)
    hi = np.full((piece.max() + 1, 3), -np.inf)
    np.minimum.at(lo, piece, V)
    np.maximum.at(hi, piece, V)
    size = float(np.max(np.linalg.norm(hi - lo, axis=1)))
    if not np.isfinite(size) or size <= 0.0:
        return [np.arange(n)]
    cube = gap_share * size
    keys, cell = np.unique(np.floor((V - V.min(axis=0)) / cube).astype(np.int64), axis=0, return_inverse=True)
    cell = cell.ravel()
    pairs = cKDTree(keys.astype(np.float64)).query_pairs(np.sqrt(3.0) + 1e-6, output_type="ndarray")
    touching = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(keys), len(keys)))
    _, cluster = connected_components(touching, directed=False)
    of_vertex = cluster[cell]
    by_cluster = np.argsort(of_vertex, kind="stable")  # one sort, not a pass over the scan per cluster
    groups = np.split(by_cluster, np.cumsum(np.bincount(of_vertex))[:-1])
    return sorted((g for g in groups if len(g)), key=len, reverse=True)


def _head_in_scan(head: TemplateHead, V: np.ndarray, scan_F: np.ndarray, s: float, R: np.ndarray,
                  t: np.ndarray) -> HeadInScan:
    """HeadInScan from the similarity x -> s R x + t taking the face frame into the scan's."""
    X = (V - t) @ R / s  # the scan in the face frame at the template's size
    keep = head_part(head, X, scan_F)
    if keep.any():
        tree = cKDTree(X[keep])
        coverage = float(np.mean(tree.query(head.face)[0] <= FACE_NEAR))
        residual = _trimmed_mean(tree.query(head.face)[0])
    else:
        coverage, residual = 0.0, np.inf
    # The face frame keeps the person's true size where the scale fits a length unit: the
    # scan is scaled about the template head's centre, so the two still overlap.
    unit, factor = scan_unit(1.0 / s)
    if unit == "unknown" or abs(np.log(factor * s)) > np.log(UNIT_SNAP):
        unit, factor = "unknown", 1.0 / s
    k = factor * s
    pivot = head.head.mean(axis=0)
    T = np.eye(4)
    T[:3, :3] = (k / s) * R.T
    T[:3, 3] = -(k / s) * R.T @ t + (1.0 - k) * pivot
    M = np.eye(4)
    M[:3, :3] = s * R
    M[:3, 3] = t
    return HeadInScan(T, unit, keep, coverage, residual, 1.0 / s, M)


def poses_agree(a: HeadInScan, b: HeadInScan) -> bool:
    """Whether two placements of the template's head in one scan place the same head: turned
    apart by at most POSE_AGREE_TURN degrees, sized within POSE_AGREE_SCALE of each other,
    their face frames' origins within POSE_AGREE_SHIFT metres (at a's size)."""
    (sa, Ra, ta), (sb, Rb, tb) = (_similarity_of(h.template_to_scan) for h in (a, b))
    turn = float(np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1.0) / 2.0, -1.0, 1.0))))
    return (turn <= POSE_AGREE_TURN and 1.0 / POSE_AGREE_SCALE <= sa / sb <= POSE_AGREE_SCALE
            and float(np.linalg.norm(ta - tb)) / sa <= POSE_AGREE_SHIFT)


def _similarity_of(M: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R (3, 3), t (3,)) of a similarity M (4, 4): x -> s R x + t."""
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    return s, M[:3, :3] / s, M[:3, 3]


def head_from_landmarks(template: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray,
                        template_points: np.ndarray, scan_points: np.ndarray) -> HeadInScan:
    """The head found from feature points given on the scan: the same feature points on the
    template (k, 3) metres and on the scan (k, 3) in its frame and unit, k >= 3. The pose
    is their least-squares similarity; the unit is snapped as in find_head."""
    V = np.asarray(scan_V, dtype=np.float64)
    head = template_head(template)
    s_ts, R_ts, t_ts = similarity_transform(np.asarray(template_points, np.float64),
                                            np.asarray(scan_points, np.float64))
    return _head_in_scan(head, V, scan_F, s_ts, R_ts, t_ts)
