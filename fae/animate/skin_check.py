"""Is the skin whole? Folds, edge strain and lips passing through each other, frame by frame.

A visible skin triangle (none of its corners in the mouth's lining, which is seen only
through the lips, and not a needle thinner than `SLIVER_HEIGHT` of the median edge) is
**folded** when its normal, in the head's own frame (head rotation removed), has turned
more than 90 degrees from its rest normal, or when it sits on a **crease**: an edge whose
two triangles (any two, around an edge of three or more on a user's head), at most 45
degrees apart at rest, are now more than 90 degrees apart (a hinge fold shows as a dark
line before either side has turned 90 degrees). Edge
**strain** is an edge's length over its rest length, over the edges of visible triangles
(not shorter than `STRAIN_MIN_EDGE` of the median edge, and not within an upper lid's
lining, both ends hidden at rest: it stretches over the eyeball unseen behind the lid's
front as the lid closes; should it come out, the lining and back checks below see it). The lips **cross** when an edge
of one lip passes through a triangle of the other (a segment-triangle test between the
two lip regions): the lower lip has gone through the upper one, or the reverse. The
**lining shows** when an edge of skin hidden at rest (the eyelids' lining behind their
margins, the backs of the ears, the nostrils: skin no outward ray leaves, the mouth and lips
left to the lip check) passes through a visible triangle near it: the lining has come out
through the skin (the cheek rising into the lower lid's lining at the outer eye corner),
and its dark back shows as a streak although no triangle has turned over (an edge that
touches the triangle at rest, within `SLIVER_HEIGHT` of the median edge, or is shorter than
`STRAIN_MIN_EDGE` of it, is not tested against it: a pit an adapted head's fit pressed flat
swaps sides at the slightest motion, unseen). The skin's
**back shows** where a viewer in front of the face (the head's own frame, looking along -z)
first meets a skin triangle from behind: rays on a `BACK_RAY_SPACING` grid over the face
(scalp, neck, ears and the mouth's lining left out of the grid's extent; a ray meeting the
mouth's lining, as dark from either side, not counted; one meeting the lips' inner edge,
where they join the lining, by its back is: a pinched mouth corner has flipped it out); the
area they cover is what a viewer sees inside out, whatever made it (a lid's margin rolled
out, a lip turned inside out, a fold), and a frame shows it when that area exceeds
`BACK_AREA_LIMIT`.

    check = SkinCheck(face)
    for name, frames in default_streams(): ...          # the FAP sweep and the six expressions
    frame_report = check.frame(skin_in_head_frame)        # FrameCheck
    stream_report = check_stream(player, frames, name)    # dict, JSON-ready
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from fae.mesh import triangle_normals, triangle_pairs
from fae.sim.build import HIDDEN_REGIONS, LIP_REGIONS, UPPER_LID_REGIONS

FOLD_COS = 0.0  # cos 90 degrees: a normal turned further than this is folded
# a crease: two neighbours at most 45 degrees apart at rest, more than 90 degrees apart now
CREASE_REST_COS = np.cos(np.radians(45.0))
MAX_STRETCH = 2.0  # what a whole skin never exceeds (edge length over rest length)
MIN_COMPRESSION = 0.3
# strain is measured on edges at least this share of the median edge: a sliver's 1-micron
# edge grown to 0.2 mm is 200x its length and invisible
STRAIN_MIN_EDGE = 0.05
# a needle (least height under this share of the median edge: 0.04 mm on the shipped head,
# which has 182 of them among 22,742 triangles) has no direction of its own to turn from:
# two of its corners a few microns apart swap sides at the slightest motion, unseen
SLIVER_HEIGHT = 0.01
# the FAP sweep, per FAP and side: up in SWEEP_STEPS steps of the range, each below the limit
# held SWEEP_STEP_HOLD frames (the skin settles there: a quarter reached in a rise of a frame a
# step read as whole where, held, it folded), the limit held SWEEP_HOLD frames, down in steps
# of a frame, then SWEEP_REST frames at rest (what shows as the skin comes back)
SWEEP_STEPS, SWEEP_STEP_HOLD, SWEEP_HOLD, SWEEP_REST = 4, 6, 8, 6
EXPRESSION_RAMP, EXPRESSION_HOLD = 8, 12
# a hidden edge is tested against the visible triangles within this many metres of it at
# rest (beyond each one's own size): the lining lies a few millimetres behind the skin
LINING_REACH = 0.003
# rays from the front 1 mm apart (27,500 over the generic head's face, 15 ms a frame); a
# frame shows the skin's back when over 3 mm^2 of it faces the viewer (the real streams'
# lids and lips leave specks of 1-2 mm^2 along their edges; a blink's rolled-out margin
# showed 50 mm^2)
BACK_RAY_SPACING = 0.001
BACK_AREA_LIMIT = 3e-6
BACK_GRID_LEFT_OUT = ("scalp", "neck", "ear_l", "ear_r", "mouth_cavity")


@dataclass
class FrameCheck:
    """One frame. folded (T,) bool per skin triangle (False where not visible): turned over
    or on a crease; turned (T,) bool: the folded triangles whose own normal has turned over
    (the rest sit on a crease); stretch and compression: the largest and smallest edge
    length over rest length of visible edges; lip_crossings: lip edges that pass through
    the other lip; lining_crossings: edges of skin hidden at rest that pass through a
    visible triangle; back_area: m^2 of the face a viewer in front sees by the skin's back;
    back_rays: (T,) int per skin triangle, the rays that meet it first and by its back
    (BACK_RAY_SPACING^2 each; empty where not measured); crossed: (V,) bool per skin
    vertex, the ends of the lip and lining edges that cross and the corners of the
    triangles they cross, and the ends of edges past the strain limits (empty where not
    measured)."""

    folded: np.ndarray
    turned: np.ndarray
    stretch: float
    compression: float
    lip_crossings: int
    lining_crossings: int = 0
    back_area: float = 0.0
    back_rays: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    crossed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


def point_triangle_distances(p: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(k,) distances of points p (k, 3) to triangles T (k, 3, 3), pair by pair: to the
    plane where the point projects inside the triangle, else to its nearest side."""
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    n = np.cross(e1, e2)
    nn = np.maximum(np.sum(n * n, axis=1), 1e-300)
    w = p - T[:, 0]
    # barycentric coordinates of the projection (u on e1, v on e2)
    u = np.sum(np.cross(w, e2) * n, axis=1) / nn
    v = np.sum(np.cross(e1, w) * n, axis=1) / nn
    inside = (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0)
    out = np.abs(np.sum(w * n, axis=1)) / np.sqrt(nn)
    side = np.full(len(p), np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        d = T[:, j] - T[:, i]
        s = np.clip(np.sum((p - T[:, i]) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300), 0.0, 1.0)
        side = np.minimum(side, np.linalg.norm(p - T[:, i] - s[:, None] * d, axis=1))
    return np.where(inside, out, side)


def segment_triangle_pairs_crossing(a: np.ndarray, b: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(...) bool: whether segment a-b (..., 3) passes through triangle T (..., 3, 3), the
    shapes broadcast against each other: Moller-Trumbore, strictly inside both (a segment
    that shares a corner with a triangle touches it, it does not cross it)."""
    d = b - a
    e1, e2 = T[..., 1, :] - T[..., 0, :], T[..., 2, :] - T[..., 0, :]
    p = np.cross(d, e2)
    det = np.sum(e1 * p, axis=-1)
    ok = np.abs(det) > 1e-18
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = a - T[..., 0, :]
    u = np.sum(s * p, axis=-1) * inv
    q = np.cross(s, e1)
    v = np.sum(d * q, axis=-1) * inv
    t = np.sum(e2 * q, axis=-1) * inv
    eps = 1e-6
    return ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)


def median_edge_length(V: np.ndarray, F: np.ndarray) -> float:
    """Metres: the median length of the first edge of each triangle F (m, 3) over V (n, 3)
    (0 without triangles), the scale of the needle and short-edge rules."""
    return float(np.median(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1))) if len(F) else 0.0


def _mouth_and_lips(face) -> np.ndarray:
    """(V,) bool: skin vertices of the mouth's lining and the lips."""
    names = list(face.region_names)
    return np.isin(np.asarray(face.skin_region), [names.index(r) for r in (*HIDDEN_REGIONS, *LIP_REGIONS) if r in names])


def hidden_at_rest(face) -> np.ndarray:
    """(V,) bool: skin vertices that no outward ray leaves at rest (fae.adapt.transfer.
    visible_skin: the lids' lining, the backs of the ears, the nostrils, a few pits), the
    mouth and lips left out (their inner sides show as soon as the mouth opens)."""
    from fae.adapt.transfer import visible_skin

    return ~visible_skin(face) & ~_mouth_and_lips(face)


def lining_pairs(face, visible_triangles: np.ndarray, reach: float = LINING_REACH,
                 hidden: np.ndarray | None = None) -> np.ndarray:
    """(k, 3) int: (edge's two skin vertices, triangle index) pairs to test per frame: each
    edge with an end that no outward ray leaves at rest (fae.adapt.transfer.visible_skin:
    the lids' lining, the backs of the ears, the nostrils, and a few pits of the chin, neck
    and scalp; the mouth and lips left out) against the triangles of `visible_triangles`
    (T,) bool with no hidden corner, within `reach` metres of it at rest beyond the
    triangle's own size, sharing no vertex with it (hidden: `hidden_at_rest(face)`, when at hand)."""
    from scipy.spatial import cKDTree

    V = np.asarray(face.skin_vertices, dtype=np.float64)
    F = np.asarray(face.skin_faces, dtype=np.int64)
    lips = _mouth_and_lips(face)
    hidden = hidden_at_rest(face) if hidden is None else hidden
    E = _triangle_edges(F[hidden[F].any(axis=1) & ~lips[F].any(axis=1)])
    E = E[hidden[E].any(axis=1)]
    tris = np.flatnonzero(visible_triangles & ~hidden[F].any(axis=1))
    if len(E) == 0 or len(tris) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    centre = V[F[tris]].mean(axis=1)
    size = np.linalg.norm(V[F[tris]] - centre[:, None], axis=2).max(axis=1)
    mid = 0.5 * (V[E[:, 0]] + V[E[:, 1]])
    half = 0.5 * np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    near = cKDTree(centre).query_ball_point(mid, reach + size.max() + half.max())
    e = np.repeat(np.arange(len(E)), [len(n) for n in near])
    t = np.concatenate([np.asarray(n, dtype=np.int64) for n in near])
    keep = np.linalg.norm(mid[e] - centre[t], axis=1) <= reach + size[t] + half[e]
    e, t = e[keep], tris[t[keep]]
    shared = (F[t] == E[e, :1]).any(axis=1) | (F[t] == E[e, 1:]).any(axis=1)
    e, t = e[~shared], t[~shared]
    # an edge that touches the triangle at rest, or has no length (a hidden pit an adapted
    # head's fit pressed flat against the skin: a 0.03 mm edge on a 0.06 mm triangle) swaps
    # sides at the slightest motion, unseen; it is a needle's case (SLIVER_HEIGHT)
    median_edge = median_edge_length(V, F)
    a, b, T = V[E[e, 0]], V[E[e, 1]], V[F[t]]
    h = SLIVER_HEIGHT * median_edge
    # within h of the triangle: through it once moved h along its normal, or near its sides
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    n *= (h / np.maximum(np.linalg.norm(n, axis=1), 1e-300))[:, None]
    touching = segment_triangle_pairs_crossing(a + n, b + n, T) | segment_triangle_pairs_crossing(a - n, b - n, T)
    touching |= np.min([point_triangle_distances(a + s * (b - a), T) for s in np.linspace(0.0, 1.0, 9)], axis=0) < h
    touching |= 2.0 * half[e] < STRAIN_MIN_EDGE * median_edge
    return np.column_stack([E[e[~touching]], t[~touching]])


class SkinCheck:
    """Precomputed rest normals, visible triangles and edges, lip regions of a FaceModel."""

    def __init__(self, face):
        self.face = face
        V = np.asarray(face.skin_vertices, dtype=np.float64)
        F = np.asarray(face.skin_faces, dtype=np.int64)
        self.faces = F
        names = list(face.region_names)
        region = np.asarray(face.skin_region)
        hidden = np.isin(region, [names.index(r) for r in HIDDEN_REGIONS if r in names])
        n = triangle_normals(V, F)
        area2 = np.linalg.norm(n, axis=1)
        # degenerate rest triangles and needles have no direction to turn from
        longest = np.linalg.norm(V[F] - V[F][:, [1, 2, 0]], axis=2).max(axis=1)
        median_edge = median_edge_length(V, F)
        sized = (area2 > 1e-14) & (area2 >= SLIVER_HEIGHT * median_edge * longest)
        self.visible = ~hidden[F].any(axis=1) & sized
        self.rest_normals = n / np.maximum(area2, 1e-30)[:, None]
        # a triangle's region: the most common of its corners' (ties: the first corner's)
        r = region[F]
        self.triangle_region = np.where(r[:, 1] == r[:, 2], r[:, 1], r[:, 0])
        self.region_names = names
        e = np.concatenate([F[self.visible][:, [0, 1]], F[self.visible][:, [1, 2]], F[self.visible][:, [2, 0]]])
        e.sort(axis=1)
        self.edges = np.unique(e, axis=0)
        # (an upper lid's lining stretches unseen: drawn down over the eyeball behind the
        # lid's front as it closes; an edge from it to skin seen at rest may be seen. Other
        # skin hidden at rest, the lower lids' lining, the ears' backs, comes into view as
        # lids open wide or the head turns: its edges count)
        hidden_skin = hidden_at_rest(face)
        upper_lids = np.isin(region, [names.index(r) for r in UPPER_LID_REGIONS if r in names])
        unseen = hidden_skin & upper_lids
        self.edges = self.edges[~unseen[self.edges].all(axis=1)]
        self.rest_length = np.linalg.norm(V[self.edges[:, 0]] - V[self.edges[:, 1]], axis=1)
        keep = self.rest_length >= STRAIN_MIN_EDGE * np.median(self.rest_length)
        self.edges, self.rest_length = self.edges[keep], self.rest_length[keep]
        # neighbouring visible triangles that meet smoothly at rest (for creases)
        a, b = triangle_pairs(F, fans=True).T  # (around an edge of three triangles or more: each two)
        smooth = self.visible[a] & self.visible[b] & (np.sum(self.rest_normals[a] * self.rest_normals[b], axis=1)
                                                      > CREASE_REST_COS)
        self.neighbours = np.column_stack([a[smooth], b[smooth]])
        self.lips = []
        if all(r in names for r in LIP_REGIONS):
            up, low = (np.flatnonzero(np.isin(r, [names.index(x)]).all(axis=1)) for x in LIP_REGIONS)
            self.lips = [(F[up], _triangle_edges(F[low])), (F[low], _triangle_edges(F[up]))]
        self.lining = lining_pairs(face, self.visible, hidden=hidden_skin)
        self.front_rays = front_ray_origins(face, self.visible)
        # the lips' inner edge, where a lip meets the mouth's lining: hidden at rest, and no
        # viewer in front ever meets it by its back first unless a lip has turned inside out
        # there (a pinched mouth corner flips it out as a dark spike beside the lips)
        lips = np.isin(region, [names.index(r) for r in LIP_REGIONS if r in names])
        self.lip_edge = sized & lips[F].any(axis=1) & hidden[F].any(axis=1)
        self._query = None

    def frame(self, skin: np.ndarray) -> FrameCheck:
        """Check one frame's skin (V, 3) metres, in the head's own frame (rotation removed)."""
        n = triangle_normals(skin, self.faces)
        cos = np.einsum("ij,ij->i", n, self.rest_normals)
        turned = self.visible & (cos < FOLD_COS * np.linalg.norm(n, axis=1))
        folded = turned.copy()
        a, b = self.neighbours[:, 0], self.neighbours[:, 1]
        crease = np.einsum("ij,ij->i", n[a], n[b]) < 0.0
        folded[a[crease]] = True
        folded[b[crease]] = True
        ratio = np.linalg.norm(skin[self.edges[:, 0]] - skin[self.edges[:, 1]], axis=1) / self.rest_length
        crossed = np.zeros(len(skin), dtype=bool)  # where they cross or strain (problem_vertices)
        crossed[self.edges[(ratio > MAX_STRETCH) | (ratio < MIN_COMPRESSION)].ravel()] = True
        crossings = 0
        for tris, edges in self.lips:
            if len(tris) == 0 or len(edges) == 0:
                continue
            pairs = segment_triangle_pairs_crossing(skin[edges[:, 0]][:, None], skin[edges[:, 1]][:, None],
                                                    skin[tris][None])
            through_lip = pairs.any(axis=1)
            crossings += int(through_lip.sum())
            crossed[edges[through_lip].ravel()] = True
            crossed[tris[pairs.any(axis=0)].ravel()] = True
        L = self.lining
        through = segment_triangle_pairs_crossing(skin[L[:, 0]], skin[L[:, 1]], skin[self.faces[L[:, 2]]])
        lining = len(np.unique(L[through, :2], axis=0))
        crossed[L[through, :2].ravel()] = True
        crossed[self.faces[L[through, 2]].ravel()] = True
        back = self.back_rays(skin, n)
        return FrameCheck(folded=folded, turned=turned, stretch=float(ratio.max(initial=1.0)),
                          compression=float(ratio.min(initial=1.0)), lip_crossings=crossings,
                          lining_crossings=lining, back_area=float(back.sum()) * BACK_RAY_SPACING ** 2,
                          back_rays=back, crossed=crossed)

    def back_rays(self, skin: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        """(T,) int: per skin triangle, the rays of the front grid (BACK_RAY_SPACING apart,
        along -z in the head's own frame) that meet it first and by its back, for skin (V, 3)
        metres in that frame (normals: its triangle normals, when at hand); their count times
        BACK_RAY_SPACING^2 is the area a viewer in front sees by the skin's back."""
        if len(self.front_rays) == 0:
            return np.zeros(len(self.faces), dtype=np.int64)
        from fae.adapt.query import MeshQuery

        if self._query is None:
            self._query = MeshQuery(skin, self.faces)
        else:
            self._query.move(skin)
        origins = self.front_rays.copy()
        origins[:, 2] = float(skin[:, 2].max()) + 0.05
        directions = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
        hit, _, tri, _ = self._query.ray_hits(origins, directions, 1.0)
        n = triangle_normals(skin, self.faces) if normals is None else normals
        tri = np.maximum(tri, 0)
        # (the mouth's lining is dark either side; the lips' inner edge is not, seen from in front)
        back = hit & (self.visible[tri] | self.lip_edge[tri]) & (n[tri, 2] < 0.0)
        return np.bincount(tri[back], minlength=len(self.faces))


def front_ray_origins(face, visible_triangles: np.ndarray, spacing: float = BACK_RAY_SPACING) -> np.ndarray:
    """(R, 3) metres: a grid `spacing` apart over the x-y extent at rest of the visible
    triangles `visible_triangles` (T,) bool of the face (those touching BACK_GRID_LEFT_OUT
    regions left out), z to be set in front of the skin of each frame."""
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    F = np.asarray(face.skin_faces, dtype=np.int64)
    names = list(face.region_names)
    region = np.asarray(face.skin_region)
    away = np.isin(region, [names.index(r) for r in BACK_GRID_LEFT_OUT if r in names])
    tris = visible_triangles & ~away[F].any(axis=1)
    if not tris.any():
        return np.zeros((0, 3))
    P = V[F[tris]].reshape(-1, 3)
    lo, hi = P.min(axis=0), P.max(axis=0)
    X, Y = np.meshgrid(np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing))
    return np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])


def _triangle_edges(F: np.ndarray) -> np.ndarray:
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)


def problem_vertices(check: "SkinCheck", r: FrameCheck) -> np.ndarray:
    """(V,) bool: the skin vertices of what keeps frame check `r` (SkinCheck.frame) from
    being whole, to show a person where: the corners of folded triangles and of triangles
    seen by their back (when the frame shows more than BACK_AREA_LIMIT of it), and what the
    check found crossing or past the strain limits (`r.crossed`: lip and lining edges
    through skin and the triangles they cross, over-strained edges)."""
    out = np.array(r.crossed, dtype=bool)
    F = check.faces
    out[F[r.folded].ravel()] = True
    if r.back_area > BACK_AREA_LIMIT:  # (specks under the limit are tolerated, as the check does)
        out[F[r.back_rays > 0].ravel()] = True
    return out


def in_head_frame(skin: np.ndarray, head: np.ndarray) -> np.ndarray:
    """(V, 3): skin posed by the head transform `head` (4, 4) taken back to the head's frame."""
    return (skin - head[:3, 3]) @ head[:3, :3]


def folded_regions(check: "SkinCheck", folded: np.ndarray) -> dict[str, int]:
    """{region name: triangles} of the skin triangles flagged in `folded` (T,) bool."""
    rid, count = np.unique(check.triangle_region[folded], return_counts=True)
    return {check.region_names[r]: int(c) for r, c in zip(rid, count)}


def what_breaks(r: FrameCheck | None) -> list[str]:
    """What keeps frame check `r` from being whole (None: skin not finite): "not finite",
    "folded", "stretched", "compressed", "lips crossed", "lining shown", "back shown";
    empty when whole (check_stream's limits)."""
    if r is None:
        return ["not finite"]
    why = []
    for bad, what in ((r.folded.any(), "folded"), (r.stretch > MAX_STRETCH, "stretched"),
                      (r.compression < MIN_COMPRESSION, "compressed"), (r.lip_crossings > 0, "lips crossed"),
                      (r.lining_crossings > 0, "lining shown"), (r.back_area > BACK_AREA_LIMIT, "back shown")):
        if bad:
            why.append(what)
    return why


@dataclass
class SideRecord:
    """One FAP's side of a sweep, as checked so far: the shares of its limit reached,
    the least share at which a frame broke (None: none did) and what broke at each share,
    the triangles ever folded (T,) bool, the extreme edge strain (None until a frame was
    measured)."""

    folded: np.ndarray
    shares: set = field(default_factory=set)
    fails_at: float | None = None
    why: dict = field(default_factory=dict)
    stretch: float | None = None
    compression: float | None = None


class PerFap:
    """A FAP sweep's checks gathered per FAP and side: how far towards the standard's limit
    each one keeps the skin whole. `add((fap, sign, share), frame_check, what_breaks)` per frame,
    `report(check)` at the end."""

    def __init__(self, triangle_count: int):
        self.triangle_count = triangle_count
        self.sides: dict[tuple[int, int], SideRecord] = {}

    def add(self, label: tuple[int, int, float], r: FrameCheck | None, why: list[str]) -> None:
        """One frame of the side `label`: its check `r` (None: skin not finite) and what
        broke in it (what_breaks(r))."""
        fap, sign, share = int(label[0]), int(label[1]), float(label[2])
        e = self.sides.setdefault((fap, sign), SideRecord(np.zeros(self.triangle_count, dtype=bool)))
        e.shares.add(share)
        if why:
            e.why.setdefault(share, set()).update(why)
            e.fails_at = share if e.fails_at is None else min(e.fails_at, share)
        if r is not None:
            e.folded |= r.folded
            e.stretch = r.stretch if e.stretch is None else max(e.stretch, r.stretch)
            e.compression = r.compression if e.compression is None else min(e.compression, r.compression)

    def report(self, check: "SkinCheck") -> list[dict]:
        """Per FAP and side, in sweep order: {"fap", "name", "side" ("+" / "-"), "limit" (FAPU
        units), "whole_to" (the largest share of the limit held with every frame up to it
        whole: 1.0 over the whole range, 0.0 when the first step already fails), "fails_at"
        (the share at which it first fails, or None), "why" (what failed there), "triangles_folded",
        "folded_by_region", "max_stretch", "min_compression" (None where no frame could be
        measured)}."""
        from fae.mpeg4.faptables import FAP_LIMITS, FAP_NAME

        out = []
        for (fap, sign), e in self.sides.items():
            below = [x for x in e.shares if e.fails_at is not None and x < e.fails_at]
            whole_to = 1.0 if e.fails_at is None else max(below, default=0.0)
            out.append({"fap": fap, "name": FAP_NAME[fap - 1], "side": "+" if sign > 0 else "-",
                        "limit": float(FAP_LIMITS[fap - 1, 1 if sign > 0 else 0]), "whole_to": whole_to,
                        "fails_at": e.fails_at, "why": sorted(e.why.get(e.fails_at, ())),
                        "triangles_folded": int(e.folded.sum()), "folded_by_region": folded_regions(check, e.folded),
                        "max_stretch": None if e.stretch is None else rounded_up(e.stretch, 3),
                        "min_compression": None if e.compression is None else rounded_down(e.compression, 3)})
        return out


def check_stream(player, frames: Iterable, name: str = "", fps: float | None = None,
                 check: SkinCheck | None = None, shown: dict | None = None) -> dict:
    """Play `frames` (a FapStream or DenseFrames) from rest and check every frame.

    Returns {"stream", "frames", "frames_not_finite" (skin positions NaN or infinite: not
    measured, and not whole), "frames_folded", "triangles_folded", "triangles_turned" (of
    those, the ones whose own normal ever turned over; the rest only sat on a crease), "folded_by_region"
    {region: triangles}, "worst_frame", "worst_frame_folded", "max_stretch", "min_compression",
    "frames_lips_crossed", "max_lip_crossings", "frames_lining_shown", "max_lining_crossings",
    "frames_back_shown", "max_back_area_mm2", "worst_back_frame", "back_by_region" {region: mm^2
    of the back seen in that worst frame}, "ok"}; ok: every frame finite, nothing folded,
    strain within [MIN_COMPRESSION, MAX_STRETCH], the lips never cross, no lining comes out
    through the skin and no frame shows the skin's back over more than BACK_AREA_LIMIT.
    A sweep (SweepFrames) plays each FAP's side from rest (what one leaves behind, down to
    a skin no longer finite, is not laid on the next) and adds "per_fap": PerFap.report's
    records, one per FAP and side; "worst_frame" and "worst_back_frame" count the sweep's
    frames from its start. shown: a dict to fill with the frame that breaks the most (by
    folded triangles, lining and lip crossings, back rays and strain past its limits; a
    finite one), to show it: "index", "skin" (V, 3) metres, "bones" and "pupil_scale" as played, and
    "problem" (V,) bool, problem_vertices of it; left empty when every frame is whole."""
    check = check or SkinCheck(player.face)
    per_fap = PerFap(len(check.faces)) if isinstance(frames, SweepFrames) else None
    if per_fap is not None:
        parts = [(start, frames[start:end], frames.labels[start:end]) for start, end in frames.sides()]
    else:
        parts = [(0, frames, None)]
    ever = np.zeros(len(check.faces), dtype=bool)
    turned = np.zeros(len(check.faces), dtype=bool)
    count = folded_frames = lip_frames = max_crossings = lining_frames = max_lining = back_frames = 0
    worst, worst_count = -1, 0
    worst_back, back_area, back_rays = -1, 0.0, np.zeros(len(check.faces), dtype=np.int64)
    stretch, compression = 1.0, 1.0
    broken = 0  # frames whose skin is not finite: nothing of it can be measured, and it is not whole
    whole = True  # every frame so far (what_breaks)
    shown_score = 0

    def played():  # (frame index in the stream, its label or None, the played frame)
        for offset, part, part_labels in parts:
            player.reset()
            for frame in player.play(part, fps=fps):
                yield offset + frame.index, None if part_labels is None else part_labels[frame.index], frame

    for index, label, frame in played():
        count += 1
        if not (np.isfinite(frame.skin_vertices).all() and np.isfinite(frame.bone_transforms["head"]).all()):
            broken += 1
            whole = False
            if label is not None:
                per_fap.add(label, None, what_breaks(None))
            continue
        skin = in_head_frame(frame.skin_vertices, frame.bone_transforms["head"])
        r = check.frame(skin)
        why = what_breaks(r)
        whole = whole and not why
        if shown is not None and why:
            score = (int(r.folded.sum()) + r.lining_crossings + r.lip_crossings
                     + (int(r.back_rays.sum()) if r.back_area > BACK_AREA_LIMIT else 0)
                     + (r.stretch > MAX_STRETCH) + (r.compression < MIN_COMPRESSION))
            if score > shown_score:
                shown_score = score
                shown.update(index=index, skin=np.array(frame.skin_vertices, dtype=np.float64),
                             bones={k: np.array(v) for k, v in frame.bone_transforms.items()},
                             pupil_scale=dict(frame.pupil_scale),
                             problem=problem_vertices(check, r))
        if label is not None:
            per_fap.add(label, r, why)
        k = int(r.folded.sum())
        if k:
            folded_frames += 1
            ever |= r.folded
            turned |= r.turned
            if k > worst_count:
                worst, worst_count = index, k
        if r.lip_crossings:
            lip_frames += 1
            max_crossings = max(max_crossings, r.lip_crossings)
        if r.lining_crossings:
            lining_frames += 1
            max_lining = max(max_lining, r.lining_crossings)
        if r.back_area > BACK_AREA_LIMIT:
            back_frames += 1
        if r.back_area > back_area:
            worst_back, back_area, back_rays = index, r.back_area, r.back_rays
        stretch, compression = max(stretch, r.stretch), min(compression, r.compression)
    player.reset()
    regions = folded_regions(check, ever)
    back_regions = {}  # mm^2 of the back seen in the worst frame, by the region of the triangles
    for rid in np.unique(check.triangle_region[back_rays > 0]):
        area = float(back_rays[check.triangle_region == rid].sum()) * BACK_RAY_SPACING ** 2 * 1e6
        back_regions[check.region_names[rid]] = round(area, 1)
    out = {"stream": name, "frames": count, "frames_not_finite": broken, "frames_folded": folded_frames, "triangles_folded": int(ever.sum()),
            "triangles_turned": int(turned.sum()),
            "folded_by_region": regions, "worst_frame": worst, "worst_frame_folded": worst_count,
            # rounded away from the limits: a stretch of 2.0003 reads 2.001, not a passing 2.0
            "max_stretch": rounded_up(stretch, 3), "min_compression": rounded_down(compression, 3),
            "frames_lips_crossed": lip_frames, "max_lip_crossings": max_crossings,
            "frames_lining_shown": lining_frames, "max_lining_crossings": max_lining,
            "frames_back_shown": back_frames, "max_back_area_mm2": round(back_area * 1e6, 1),
            "worst_back_frame": worst_back, "back_by_region": back_regions, "ok": whole}
    if per_fap is not None:
        out["per_fap"] = per_fap.report(check)
    return out


def rounded_up(x: float, places: int) -> float:
    """x rounded up to `places` decimals (a stretch just past its limit never reads as within it)."""
    scale = 10.0 ** places
    return math.ceil(x * scale - 1e-6) / scale


def rounded_down(x: float, places: int) -> float:
    """x rounded down to `places` decimals (a compression just under its limit)."""
    scale = 10.0 ** places
    return math.floor(x * scale + 1e-6) / scale


class SweepFrames(list):
    """Frames (68,) of a FAP sweep, each labelled (FAP, +1 or -1, the share of the FAP's limit
    reached): a step's own share while the stream climbs, then 1.0 while it holds the limit,
    comes back and rests (what the skin does then comes of having been at the limit).
    `check_stream` plays each FAP's side from rest on its own."""

    def __init__(self, frames=(), labels=()):
        super().__init__(frames)
        self.labels = list(labels)

    def sides(self) -> list[tuple[int, int]]:
        """(start, end) frame ranges of the sweep's sides, one FAP and sign each."""
        out, start = [], 0
        for i in range(1, len(self.labels) + 1):
            if i == len(self.labels) or self.labels[i][:2] != self.labels[start][:2]:
                out.append((start, i))
                start = i
        return out


def sweep_shape() -> tuple[np.ndarray, np.ndarray]:
    """(amplitude, share reached) per frame of one side of the sweep, both (n,) in [0, 1]
    of the FAP's limit (see SWEEP_STEPS)."""
    steps = np.arange(1, SWEEP_STEPS + 1) / SWEEP_STEPS
    rise = np.repeat(steps[:-1], SWEEP_STEP_HOLD)
    amplitude = np.concatenate([rise, np.ones(SWEEP_HOLD), steps[::-1][1:], np.zeros(SWEEP_REST)])
    return amplitude, np.concatenate([rise, np.ones(len(amplitude) - len(rise))])


def fap_sweep(faps: Iterable[int] | None = None) -> SweepFrames:
    """(68,) frames, FAPU units: every low-level FAP 3..68 (or those of `faps`) alone, 0 -> its
    upper limit (held) -> 0 (rest), then the same to its lower limit, the limits the Player
    clamps to (`FAP_LIMITS`, the standard's ranges), climbing in steps held until the skin
    settles (sweep_shape); labelled per frame (SweepFrames) for `check_stream`'s report per
    FAP."""
    from fae.mpeg4.faptables import FAP_LIMITS
    from fae.mpeg4.faps import FAP_COUNT

    shape, reached = sweep_shape()
    out = SweepFrames()
    for k in range(3, FAP_COUNT + 1) if faps is None else sorted(set(int(f) for f in faps)):
        for limit in FAP_LIMITS[k - 1, ::-1]:
            if limit == 0.0:
                continue
            for a, share in zip(shape, reached):
                v = np.zeros(FAP_COUNT)
                v[k - 1] = a * limit
                out.append(v)
                out.labels.append((k, 1 if limit > 0 else -1, float(share)))
    return out


def expression_sweep() -> list[np.ndarray]:
    """(68,) frames: the standard's six expressions (FAP 2: joy, sadness, anger, fear,
    disgust, surprise) one after another at full intensity: rise, hold, release."""
    from fae.animate.highlevel import EXPRESSION_FAPS

    ramp = np.linspace(0.0, 1.0, EXPRESSION_RAMP + 1)[1:]
    shape = np.concatenate([ramp, np.ones(EXPRESSION_HOLD), ramp[::-1][1:], [0.0]])
    return [np.asarray(EXPRESSION_FAPS[code], dtype=np.float64) * a for code in range(1, 7) for a in shape]


def default_streams() -> list[tuple[str, list[np.ndarray]]]:
    """(name, frames): what `fae verify-skin` plays when given no stream."""
    return [("fap-sweep (every FAP alone to its limits)", fap_sweep()),
            ("expressions (FAP 2, six at full intensity)", expression_sweep())]
