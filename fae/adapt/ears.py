"""The ears of a scan, found by their shape, so the fit can place the template's there.

    found_ears(template, scan, partial=False, placement=None) -> ([Ear], report)
    ear_pairs(template, scan, partial=False, placement=None) -> ((faces (k,), bary (k, 3), points (k, 3)) or None, report)
    ears_carried(P, X, ears) -> X (n, 3): the skin with each found ear carried there

No face-landmark model sees ears, and a scan's ears may sit centimetres from where the
template's fall after the face is placed (a marble bust's 4.5 cm lower): the fit then
draws the template's ear as a flat leaf on the scalp above the scan's. An ear is what
stands out of the side of the head. Per side, the head is seen from that side: a height
map (how far out the surface reaches, |x|, over a grid in y and z, SIDE_WINDOW around the
template ear's centre, by ray casts), opened by a disc of OPEN_RADIUS (a grey-scale
opening keeps the skull's round side and drops whatever is narrower than the disc: ears,
curls, the leaves of a wreath). Where the map stands more than EAR_HEIGHT above its
opening is a candidate; the ear is the candidate of plausible area, within EAR_REACH,
that the template ear's footprint (the cells its triangles show in the same map of the
template) overlaps best when shifted onto it (the shift, by FFT correlation, starts the
ICP). The two ears' vertices seen from the side are then aligned by rigid trimmed ICP
both ways (the closer kept: hair may hide part of the scan's ear, and more of an ear may
stand out of a flatter side than of the template's); a turn beyond MAX_TURN or a residual
beyond MAX_RESIDUAL drops the ear. Template ear vertices so moved, put onto the scan,
become corresponding points for the fit (fae.adapt.nonrigid, through fae.adapt.from_scan).

All of it is done at the template's size: the scan is brought there by the scale of the
fit's start placement (`placement`, fae.adapt.nonrigid.start_placement), about where that
puts the template's middle (its turn is left out: the ears are looked for as the face
frame holds them; with it, the marble bust's ears turned 26 degrees and were dropped), so
a head 0.75x or 1.35x the template's has ears of the size looked for, where they are
looked for, and the gates mean the same (on the scan as it is, a 0.85x front half's ears
were not found at all, a 0.75x one's rejected as a poor match, and a 1.35x head's ear
pairs lay 8-13 mm off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft, ndimage
from scipy.spatial import cKDTree

from fae.adapt.binding import coverage_weights
from fae.adapt.calibration import similarity_icp
from fae.adapt.errors import Surface
from fae.adapt.query import MeshQuery
from fae.io.facemodel import FaceModel

SIDE_WINDOW = 0.08  # m: the side map reaches this far from the template ear's centre in y and z
CELL = 0.0015  # m: the side map's grid step
OPEN_RADIUS = 0.02  # m: what is narrower than this disc stands out of the side
EAR_HEIGHT = 0.004  # m: points standing out of the side more than this are ear
# a candidate's area (side view) in shares of the template ear's footprint: a clean ear
# 0.5-1.4 (the menpo3d mask's, with the mask's rim, 1.34-1.39); merged with curls 1.46-1.53
EAR_AREA = (0.3, 1.45)
EAR_REACH = 0.07  # m: the footprint's shift onto a candidate (y, z) is at most this
MIN_EAR_POINTS = 30
MAX_TURN = 25.0  # degrees (a sculpted helix alone, slid round a whole ear, turns 33)
MAX_RESIDUAL = 0.003  # m, trimmed RMS of the ICP (sculpted ears: 2.0-2.9)
# on a scan of part of the head, its rim seen from the side stands out like an ear: an ear
# found farther than this from the template's is taken for the rim (the menpo3d mask's ears
# 2.1 cm; the rims of the meshmonk face and of the suite's front halves cut at the ears
# 5.3-7.1 cm, which carried the template's ears there and swelled the jaw). A whole head's
# ears may sit farther (a marble bust's 4.8 cm low from the template's as it is, 2.2 cm from
# where the placement puts them). Metres at the template's size (the scan is brought to it by
# the scale of the fit's start placement)
PARTIAL_SCAN_EAR_REACH = 0.04
PAIRS_PER_EAR = 40
PROJECT_REACH = 0.005  # m: a mapped ear point is put onto the scan when this close
EAR_FADE = 0.06  # m: the skin this far around an ear follows it when it is carried


@dataclass
class SideMap:
    """The head seen from one side: lateral reach `height` (ny, nz) metres (NaN: no
    surface), its opening `opened` (ny, nz), the triangle seen `face` (ny, nz) (-1: none),
    over cells from (y0, z0) in steps of CELL."""

    side: float
    y0: float
    z0: float
    height: np.ndarray
    opened: np.ndarray
    face: np.ndarray

    def cells(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grid cell (i, j) of points X (n, 3), and whether it lies on the map."""
        i = np.floor((X[:, 1] - self.y0) / CELL).astype(np.int64)
        j = np.floor((X[:, 2] - self.z0) / CELL).astype(np.int64)
        on = (i >= 0) & (i < self.height.shape[0]) & (j >= 0) & (j < self.height.shape[1])
        return np.clip(i, 0, self.height.shape[0] - 1), np.clip(j, 0, self.height.shape[1] - 1), on

    def seen(self, X: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """(n,) bool: points X (n, 3) over `cells` (ny, nz) bool that are seen from the side
        (within EAR_HEIGHT of the surface the map shows there)."""
        i, j, on = self.cells(X)
        return on & cells[i, j] & (self.side * X[:, 0] > np.nan_to_num(self.height[i, j], nan=np.inf) - EAR_HEIGHT)


def side_map(query: MeshQuery, side: float, centre: np.ndarray) -> SideMap:
    """The surface in `query` seen from side +1 (left, +x) or -1 (right) around `centre` (3,)."""
    y0, z0 = centre[1] - SIDE_WINDOW, centre[2] - SIDE_WINDOW
    n = int(round(2 * SIDE_WINDOW / CELL))
    Y, Z = np.meshgrid(y0 + CELL * (np.arange(n) + 0.5), z0 + CELL * (np.arange(n) + 0.5), indexing="ij")
    far = float(np.abs(query.V[:, 0]).max()) + 0.1
    origins = np.c_[np.full(Y.size, side * far), Y.ravel(), Z.ravel()]
    hit, t, face, _ = query.ray_hits(origins, np.tile([-side, 0.0, 0.0], (Y.size, 1)), 2.0 * far)
    height = np.where(hit, far - t, np.nan).reshape(Y.shape)
    r = int(round(OPEN_RADIUS / CELL))
    yy, zz = np.mgrid[-r:r + 1, -r:r + 1]
    floor = np.nanmin(height) - 0.1 if np.isfinite(height).any() else 0.0
    opened = ndimage.grey_opening(np.where(np.isnan(height), floor, height), footprint=yy ** 2 + zz ** 2 <= r * r)
    return SideMap(side, y0, z0, height, np.where(np.isnan(height), np.nan, opened), face.reshape(Y.shape))


def ear_offset(t_cells: np.ndarray, s_cells: np.ndarray) -> tuple[np.ndarray, float]:
    """The shift (di, dj) (2,) int, in cells, that lays the template ear's footprint t_cells
    (ny, nz) bool best onto the candidate s_cells (same grid), and their overlap over union
    there."""
    # full cross-correlation by FFT (scipy.fft: scipy.signal's import alone took 0.35 s of
    # every adapt)
    shape = [a + b - 1 for a, b in zip(s_cells.shape, t_cells.shape)]
    padded = [fft.next_fast_len(n, real=True) for n in shape]
    score = fft.irfft2(fft.rfft2(s_cells.astype(float), padded) * fft.rfft2(t_cells[::-1, ::-1].astype(float), padded),
                       padded)[:shape[0], :shape[1]]
    k = np.argmax(score)
    shift = np.array(np.unravel_index(k, score.shape)) - (np.array(t_cells.shape) - 1)
    overlap = float(score.flat[k])
    return shift, overlap / max(t_cells.sum() + s_cells.sum() - overlap, 1.0)


def ear_cells(m: SideMap, t_cells: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The scan's ear on a side map: of the candidates (cells standing out more than
    EAR_HEIGHT) of plausible area (EAR_AREA x the template ear's footprint t_cells (ny, nz)
    bool, on the same grid), the one that matches the footprint best (overlap over union)
    within EAR_REACH of where the template has it. Returns its cells (ny, nz) bool and the
    footprint's shift onto it (2,) int, in cells; None when there is none."""
    out = np.nan_to_num(m.height - m.opened, nan=0.0) > EAR_HEIGHT
    label, count = ndimage.label(out)
    area = t_cells.sum()
    best, best_score = None, 0.0
    for k in range(1, count + 1):
        cells = label == k
        if not (EAR_AREA[0] * area <= cells.sum() <= EAR_AREA[1] * area):
            continue
        shift, score = ear_offset(t_cells, cells)
        if np.linalg.norm(shift) * CELL <= EAR_REACH and score > best_score:
            best, best_score = (cells, shift), score
    return best


def ear_shift(t_map: SideMap, t_cells: np.ndarray, s_map: SideMap, shift: np.ndarray) -> np.ndarray:
    """(3,) metres from the template's ear (footprint t_cells on t_map) to the scan's (on
    s_map, the same grid) for a shift (2,) in cells: laterally, the median difference of
    the two maps' heights over the footprint so shifted."""
    i, j = np.nonzero(t_cells)
    i2, j2 = i + shift[0], j + shift[1]
    on = (i2 >= 0) & (i2 < s_map.height.shape[0]) & (j2 >= 0) & (j2 < s_map.height.shape[1])
    lateral = s_map.height[i2[on], j2[on]] - t_map.height[i[on], j[on]]
    dx = float(np.nanmedian(lateral)) if np.isfinite(lateral).any() else 0.0
    return np.array([t_map.side * dx, shift[0] * CELL, shift[1] * CELL])


def ear_rigid(A: np.ndarray, B: np.ndarray, t0: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """x -> R x + t carrying the template's ear points A (n, 3) onto the scan's B (m, 3),
    and its trimmed RMS (metres), by rigid ICP from the shift t0 (3,) both ways, the closer
    kept: hair may hide part of the scan's ear (scan onto template then fits), and more of
    an ear may stand out of a flatter side than of the template's (template onto scan then
    fits). Rigid: a scaled ICP between ears that overlap in part shrinks or swells the ear."""
    _, R, t, rms = similarity_icp(A, cKDTree(B), B, 1.0, np.eye(3), t0, iterations=30, keep=0.8, with_scale=False)
    _, R_back, t_back, rms_back = similarity_icp(B, cKDTree(A), A, 1.0, np.eye(3), -t0, iterations=30, keep=0.8,
                                                 with_scale=False)
    if rms_back < rms:
        return R_back.T, -R_back.T @ t_back, rms_back
    return R, t, rms


@dataclass
class Ear:
    """An ear found on the scan: the template's `vertices` (k,) of that ear carried there
    by x -> R x + t (R (3, 3): a rotation times the person's size over the template's; t
    (3,) metres, face frame), and corresponding points for the
    fit: template skin `faces` (p,), `bary` (p, 3), scan `points` (p, 3) metres."""

    name: str
    vertices: np.ndarray
    R: np.ndarray
    t: np.ndarray
    faces: np.ndarray
    bary: np.ndarray
    points: np.ndarray


def found_ears(template: FaceModel, scan: Surface, partial: bool = False,
               placement: np.ndarray | None = None) -> tuple[list[Ear], dict]:
    """The template's ears found on a scan (in the face frame, metres, head part only), and a
    report per ear (found or why not). placement: (4, 4) the map placing the template on
    the scan (the fit's start: fae.adapt.nonrigid.start_placement; default none): the
    search runs on the scan brought to the template's size by its scale (see above), so the
    report's lengths (moved_m, residual_m) are at the template's size.
    partial: the scan covers only part of the head (as the fit's start finds it): an ear
    found farther than PARTIAL_SCAN_EAR_REACH from the template's is its rim. Each Ear's
    map and points are the scan's."""
    P = np.asarray(template.skin_vertices, dtype=np.float64)
    # M: the template's size to the scan's (the placement's scale about where it puts the
    # template's middle; not its turn). The scan brought back by it: the side maps, areas,
    # heights and gates below are at the template's size
    M = np.eye(4)
    scan_V, scan_query = scan.V, scan.query
    if placement is not None:
        placement = np.asarray(placement, dtype=np.float64)
        middle = P.mean(axis=0)
        size = float(abs(np.linalg.det(placement[:3, :3]))) ** (1.0 / 3.0)
        M[:3, :3] = size * np.eye(3)
        M[:3, 3] = placement[:3, :3] @ middle + placement[:3, 3] - size * middle
        scan_V = (scan.V - M[:3, 3]) / size
        scan_query = MeshQuery(scan_V, scan.F)
    F = np.asarray(template.skin_faces, dtype=np.int64)
    region = np.asarray(template.skin_region)
    # a triangle holding each vertex, and the vertex's corner in it
    corner_face = np.full(len(P), -1, dtype=np.int64)
    corner = np.zeros(len(P), dtype=np.int64)
    for k in range(3):
        corner_face[F[:, k]] = np.arange(len(F))
        corner[F[:, k]] = k
    template_query = MeshQuery(P, F)
    ears, report = [], {}
    for name, side in (("ear_l", 1.0), ("ear_r", -1.0)):
        if name not in template.region_names:
            continue
        ear = region == template.region_names.index(name)
        if not ear.any():
            continue
        centre = P[ear].mean(axis=0)
        t_map = side_map(template_query, side, centre)
        # the template's ear as seen from the side: every cell showing one of its triangles
        t_cells = (t_map.face >= 0) & ear[F[np.maximum(t_map.face, 0)]].any(axis=-1)
        if t_cells.sum() * CELL * CELL < 1e-4:
            report[name] = {"found": False, "why": "the template's ear is not seen from the side"}
            continue
        s_map = side_map(scan_query, side, centre)
        found = ear_cells(s_map, t_cells)
        if found is None:
            report[name] = {"found": False, "why": "nothing of an ear's size stands out of the scan's side"}
            continue
        s_cells, shift = found
        # each ear's vertices on the side seen (not the back of the ear, nor the head behind it)
        s_ear = np.flatnonzero(s_map.seen(scan_V, ndimage.binary_dilation(s_cells, iterations=2)))
        t_ear = np.flatnonzero(ear & t_map.seen(P, t_cells))
        if len(s_ear) < MIN_EAR_POINTS or len(t_ear) < MIN_EAR_POINTS:
            report[name] = {"found": False, "why": f"{len(s_ear)} scan points and {len(t_ear)} template points "
                                                   f"seen of the ear (at least {MIN_EAR_POINTS} each)"}
            continue
        A = P[t_ear]
        R, t, rms = ear_rigid(A, scan_V[s_ear], ear_shift(t_map, t_cells, s_map, shift))
        turn = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
        entry = {"scan_points": int(len(s_ear)), "turn_degrees": turn, "residual_m": rms,
                 "moved_m": float(np.linalg.norm(R @ A.mean(axis=0) + t - A.mean(axis=0)))}
        if not (turn <= MAX_TURN and rms <= MAX_RESIDUAL):
            report[name] = {"found": False, "why": "the ear found does not match the template's", **entry}
            continue
        if partial and entry["moved_m"] > PARTIAL_SCAN_EAR_REACH:
            report[name] = {"found": False, "why": "on a scan of part of the head, what stands out this far from "
                                                   "the template's ear is taken for the scan's rim", **entry}
            continue
        pick = t_ear[np.linspace(0, len(t_ear) - 1, min(PAIRS_PER_EAR, len(t_ear))).astype(int)]
        on_scan, _, tri, _ = scan_query.closest_points(P[pick] @ R.T + t, PROJECT_REACH)
        ok = (tri >= 0) & (corner_face[pick] >= 0)
        if ok.sum() < MIN_EAR_POINTS // 3:
            report[name] = {"found": False, "why": "the mapped ear lies off the scan", **entry}
            continue
        bary = np.zeros((int(ok.sum()), 3))
        bary[np.arange(len(bary)), corner[pick[ok]]] = 1.0
        # back to the scan: the points, and the map (then the person's size, not a rotation)
        ears.append(Ear(name, np.flatnonzero(ear), M[:3, :3] @ R, M[:3, :3] @ t + M[:3, 3], corner_face[pick[ok]],
                        bary, on_scan[ok] @ M[:3, :3].T + M[:3, 3]))
        report[name] = {"found": True, "pairs": int(ok.sum()), **entry}
    return ears, report


def ear_pairs(template: FaceModel, scan: Surface, partial: bool = False, placement: np.ndarray | None = None
              ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, dict]:
    """Corresponding points on the template's ears and the scan's (see found_ears): (faces
    (k,), bary (k, 3), points (k, 3) metres) or None when no ear was found, and the report."""
    ears, report = found_ears(template, scan, partial, placement)
    if not ears:
        return None, report
    return (np.concatenate([e.faces for e in ears]), np.vstack([e.bary for e in ears]),
            np.vstack([e.points for e in ears])), report


def ears_carried(P: np.ndarray, X: np.ndarray, ears: list[Ear]) -> np.ndarray:
    """(n, 3) metres: the skin X (n, 3) (the template P (n, 3) placed on the scan) with each
    ear carried to where `ears` found it (P's ear vertices moved by the ear's R, t: turned,
    and scaled to the person's size)
    and the skin around along with it, by a weight falling smoothly (smoothstep of the
    distance to the ear, in P) to 0 at EAR_FADE. An ear moved 4.5 cm folds some skin
    between it and the jaw; the fit blends that back (fae.adapt.nonrigid.fit_to_scan).
    Wider (8-10 cm) folds none, but reaches the jaw's angle, and the mandible carried
    with the skin came out through it on a marble bust."""
    Y = np.asarray(X, dtype=np.float64).copy()
    for e in ears:
        w = coverage_weights(cKDTree(P[e.vertices]).query(P)[0], 0.0, EAR_FADE)
        Y += w[:, None] * (P @ e.R.T + e.t - Y)
    return Y
