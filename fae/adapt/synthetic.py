"""Synthetic heads with known ground truth, for tests and benchmarks of the fitting.

A head is a star-shaped surface r(d) around the origin (an ellipsoid with a nose, brow
ridge, chin and cheek bones), in the MPEG-4 face frame (metres, +z forward, +y up, the
face's left is +x). Its feature points are the surface points in fixed directions, so
they are exact. A "scan" of a different person is the same kind of surface, sampled by
differently placed vertices, moved by a smooth random warp plus fine detail, optionally
noisy, holed, cropped to the face and placed in another frame and unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

# Feature point directions as (azimuth about +y from +z towards +x, elevation), radians.
_FDP_DIRECTIONS = {
    "2.1": (0.0, -0.62),
    "2.10": (0.0, -0.50),
    "2.13": (0.95, -0.42),
    "2.14": (-0.95, -0.42),
    "3.7": (0.50, 0.12),
    "3.11": (0.17, 0.12),
    "3.8": (-0.17, 0.12),
    "3.12": (-0.50, 0.12),
    "4.3": (0.33, 0.27),
    "4.4": (-0.33, 0.27),
    "5.3": (0.55, -0.05),
    "5.4": (-0.55, -0.05),
    "8.1": (0.0, -0.22),
    "8.2": (0.0, -0.34),
    "8.3": (0.30, -0.28),
    "8.4": (-0.30, -0.28),
    "9.3": (0.0, -0.02),
    "9.15": (0.0, -0.12),
    "10.9": (1.45, 0.05),
    "10.10": (-1.45, 0.05),
    "11.1": (0.0, 0.62),
    "11.4": (0.0, 1.45),
    "11.6": (np.pi, 0.15),
}

_SEMI_AXES = np.array([0.078, 0.112, 0.098])  # metres: half width, half height, half depth


def _unit_directions(azimuth_elevation: np.ndarray) -> np.ndarray:
    az, el = azimuth_elevation[:, 0], azimuth_elevation[:, 1]
    return np.column_stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])


def _bump(d: np.ndarray, centre: tuple[float, float], width: float, height: float) -> np.ndarray:
    c = _unit_directions(np.array([centre]))[0]
    return height * np.exp(-np.sum((d - c) ** 2, axis=1) / (2.0 * width**2))


def head_radius(d: np.ndarray, shape: np.ndarray | None = None) -> np.ndarray:
    """(n,) metres: the head surface's distance from the origin along unit directions d (n, 3).

    `shape` (6,) scales the features (nose, brows, chin, cheeks, width, height) around 1.
    """
    s = np.ones(6) if shape is None else np.asarray(shape, dtype=np.float64)
    axes = _SEMI_AXES * np.array([s[4], s[5], 1.0])
    r = 1.0 / np.sqrt(np.sum((d / axes) ** 2, axis=1))
    r = r + _bump(d, (0.0, -0.03), 0.07, 0.026 * s[0])   # nose
    r = r + _bump(d, (0.0, 0.06), 0.05, 0.006 * s[0])    # nose bridge
    r = r + _bump(d, (0.33, 0.22), 0.09, 0.007 * s[1]) + _bump(d, (-0.33, 0.22), 0.09, 0.007 * s[1])
    r = r - _bump(d, (0.33, 0.12), 0.07, 0.008) - _bump(d, (-0.33, 0.12), 0.07, 0.008)  # eye sockets
    r = r + _bump(d, (0.0, -0.50), 0.10, 0.010 * s[2])  # chin
    r = r + _bump(d, (0.55, -0.05), 0.10, 0.006 * s[3]) + _bump(d, (-0.55, -0.05), 0.10, 0.006 * s[3])
    r = r + _bump(d, (0.0, -0.25), 0.06, 0.006)  # lips
    return r


def head_feature_points(shape: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """FDP name -> (3,) metres on the synthetic head surface."""
    names = list(_FDP_DIRECTIONS)
    d = _unit_directions(np.array([_FDP_DIRECTIONS[n] for n in names]))
    p = d * head_radius(d, shape)[:, None]
    return {n: p[i] for i, n in enumerate(names)}


def synthetic_head(subdivisions: int = 4, shape: np.ndarray | None = None,
                   rotation: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """A closed synthetic head: V (n, 3) metres, F (m, 3) int32, FDP name -> (3,) metres.

    subdivisions: icosphere level (4: 2,562 vertices, 5: 10,242, 6: 40,962, 7: 163,842).
    rotation (3, 3): turns the sampling sphere first, so two heads do not share vertices.
    """
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    d = np.asarray(sphere.vertices, dtype=np.float64)
    if rotation is not None:
        d = d @ np.asarray(rotation).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    V = d * head_radius(d, shape)[:, None]
    return V, np.asarray(sphere.faces, dtype=np.int32), head_feature_points(shape)


@dataclass
class Warp:
    """A smooth random displacement field plus fine detail along the radial direction.

    centres (k, 3), amplitudes (k, 3) metres, width metres; detail_amplitude metres,
    detail_frequency radians per metre.
    """

    centres: np.ndarray
    amplitudes: np.ndarray
    width: float
    detail_amplitude: float
    detail_frequency: float
    detail_phase: np.ndarray

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) metres: the warped positions of points X (n, 3) metres."""
        X = np.asarray(X, dtype=np.float64)
        d2 = np.sum((X[:, None, :] - self.centres[None, :, :]) ** 2, axis=2)
        out = X + np.exp(-d2 / (2.0 * self.width**2)) @ self.amplitudes
        radial = X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)
        f, ph = self.detail_frequency, self.detail_phase
        detail = np.sin(f * X[:, 0] + ph[0]) * np.sin(f * X[:, 1] + ph[1]) * np.sin(f * X[:, 2] + ph[2])
        return out + (self.detail_amplitude * detail)[:, None] * radial


def random_warp(seed: int, amplitude: float = 0.008, detail: float = 0.0008) -> Warp:
    """A Warp with 12 Gaussian centres of `amplitude` metres and detail of `detail` metres."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(12, 3)) * _SEMI_AXES
    return Warp(centres=centres, amplitudes=rng.normal(size=(12, 3)) * amplitude, width=0.05,
                detail_amplitude=detail, detail_frequency=2 * np.pi / 0.02,
                detail_phase=rng.uniform(0, 2 * np.pi, 3))


@dataclass
class SyntheticScan:
    """A scan with ground truth.

    vertices (n, 3), faces (m, 3): the scan in its own frame and unit.
    landmarks: FDP name -> (3,) in the scan's frame and unit.
    truth_vertices (n, 3) metres: the clean scan surface in the face frame (before noise),
    truth_faces; warp: face-frame point -> its ground-truth image; to_scan (4, 4): face
    frame (metres) -> scan frame and unit.
    """

    vertices: np.ndarray
    faces: np.ndarray
    landmarks: dict[str, np.ndarray]
    truth_vertices: np.ndarray
    truth_faces: np.ndarray
    warp: Warp
    to_scan: np.ndarray


def _random_rotation(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return trimesh.transformations.rotation_matrix(rng.uniform(-max_angle, max_angle), axis)[:3, :3]


def synthetic_scan(seed: int = 0, subdivisions: int = 6, noise: float = 0.0, holes: int = 0,
                   face_only: bool = False, unit: float = 1e-3, max_angle: float = 0.6,
                   amplitude: float = 0.008, detail: float = 0.0008) -> SyntheticScan:
    """A warped, resampled synthetic head placed in a random frame.

    noise: standard deviation (metres) of displacement along vertex normals.
    holes: number of round holes cut into the face (radius 8 mm), never at a feature point.
    face_only: keep only the front (z > -0.01 m in the face frame).
    unit: metres per scan unit (1e-3: the scan is in millimetres).
    max_angle: radians of the random rotation of the scan frame.
    """
    rng = np.random.default_rng(seed)
    shape = rng.uniform(0.7, 1.3, 6)
    shape[4:] = rng.uniform(0.9, 1.1, 2)
    V, F, fdp = synthetic_head(subdivisions, shape, rotation=_random_rotation(rng, np.pi))
    warp = random_warp(seed + 1000, amplitude, detail)
    W = warp(V)
    mesh = trimesh.Trimesh(W, F, process=False)
    keep = np.ones(len(F), dtype=bool)
    centroids = mesh.triangles_center
    if face_only:
        keep &= V[F].mean(axis=1)[:, 2] > -0.01
    landmark_points = warp(np.array(list(fdp.values())))
    front = V[:, 2] > 0.02
    for _ in range(holes):
        for _attempt in range(50):
            c = W[rng.choice(np.flatnonzero(front))]
            if np.min(np.linalg.norm(landmark_points - c, axis=1)) > 0.014:
                break
        keep &= np.linalg.norm(centroids - c, axis=1) > 0.008
    return _scan_of_truth(W, F[keep], landmark_points, list(fdp), warp, rng, noise, max_angle, unit)


def template_warp(V: np.ndarray, seed: int, amplitude: float = 0.006, detail: float = 0.0005,
                  width: float = 0.06) -> Warp:
    """A Warp for a head whose vertices V (n, 3) metres are given: 12 Gaussian centres spread
    over V's bounding box (width `width` metres, amplitude `amplitude` metres per axis), and
    radial detail of `detail` metres about V's bounding-box centre."""
    rng = np.random.default_rng(seed)
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre = 0.5 * (lo + hi)
    centres = rng.uniform(lo, hi, size=(12, 3)) - centre
    return _CentredWarp(centres=centres, amplitudes=rng.normal(size=(12, 3)) * amplitude, width=width,
                        detail_amplitude=detail, detail_frequency=2 * np.pi / 0.02,
                        detail_phase=rng.uniform(0, 2 * np.pi, 3), centre=centre)


@dataclass
class _CentredWarp(Warp):
    """A Warp applied about `centre` (3,) metres instead of the origin."""

    centre: np.ndarray = None

    def __call__(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        return super().__call__(X - self.centre) + self.centre


def surface_without(V: np.ndarray, F: np.ndarray, drop_faces: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The surface V (n, 3), F (m, 3) less the faces flagged in drop_faces (m,) bool, its
    unreferenced vertices removed: (V' (k, 3), F' (m', 3))."""
    F = np.asarray(F, dtype=np.int64)
    if drop_faces is not None:
        F = F[~np.asarray(drop_faces, dtype=bool)]
    mesh = trimesh.Trimesh(np.asarray(V, dtype=np.float64), F, process=False)
    mesh.remove_unreferenced_vertices()
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def template_scan(V: np.ndarray, F: np.ndarray, landmarks: dict[str, np.ndarray], seed: int = 0,
                  subdivisions: int = 1, drop_faces: np.ndarray | None = None, noise: float = 0.0,
                  holes: int = 0, face_only: bool = False, unit: float = 1e-3, max_angle: float = 0.6,
                  amplitude: float = 0.006, detail: float = 0.0005) -> SyntheticScan:
    """A "scan" of another person made from a template head (V (n, 3) metres, F (m, 3),
    landmarks FDP name -> (3,) metres on it): the surface is remeshed by `subdivisions`
    Loop steps (each x4 faces; vertices move, so no scan vertex is a template vertex),
    faces flagged in `drop_faces` (m,) bool are left out first (e.g. the mouth cavity, which
    a scanner does not see), then the result is warped by template_warp(seed), optionally
    noisy (`noise` metres along normals), holed (round holes of 8 mm radius away from the
    landmarks), cropped to the front (`face_only`: z > 0.2 of the depth behind the
    bounding-box centre), turned by up to `max_angle` radians and written in `unit` metres.

    The returned landmarks are the warped template landmarks (exact up to the Loop
    smoothing, well under a millimetre); `warp` maps template points to their truth.
    """
    rng = np.random.default_rng(seed)
    V = np.asarray(V, dtype=np.float64)
    SV, SF = surface_without(V, F, drop_faces)
    if subdivisions > 0:
        SV, SF = trimesh.remesh.subdivide_loop(SV, SF, iterations=subdivisions)
    warp = template_warp(V, seed + 1000, amplitude, detail)
    names = list(landmarks)
    L = np.array([landmarks[n] for n in names])
    W = warp(SV)
    WL = warp(L)
    keep = np.ones(len(SF), dtype=bool)
    centroids = W[SF].mean(axis=1)
    if face_only:
        lo, hi = V.min(axis=0), V.max(axis=0)
        keep &= SV[SF].mean(axis=1)[:, 2] > 0.5 * (lo[2] + hi[2]) - 0.2 * (hi[2] - lo[2])
        keep &= SV[SF].mean(axis=1)[:, 1] > lo[1] + 0.25 * (hi[1] - lo[1])  # no neck
    front = np.flatnonzero(SV[:, 2] > np.percentile(SV[:, 2], 70))
    for _ in range(holes):
        for _attempt in range(50):
            c = W[rng.choice(front)]
            if np.min(np.linalg.norm(WL - c, axis=1)) > 0.014:
                break
        keep &= np.linalg.norm(centroids - c, axis=1) > 0.008
    return _scan_of_truth(W, SF[keep], WL, list(names), warp, rng, noise, max_angle, unit)


def _scan_of_truth(W, F, landmark_points, names, warp, rng, noise, max_angle, unit) -> "SyntheticScan":
    """The scan of true surface (W (n, 3) metres, F (m, 3)): unreferenced vertices dropped,
    normal noise (metres), a random pose and the scan's unit (scan = face frame / unit)."""
    truth = trimesh.Trimesh(W, F, process=False)
    truth.remove_unreferenced_vertices()
    Vt, Ft = np.asarray(truth.vertices), np.asarray(truth.faces, dtype=np.int32)
    Vn = Vt.copy()
    if noise > 0:
        Vn = Vn + truth.vertex_normals * rng.normal(scale=noise, size=(len(Vt), 1))
    R = _random_rotation(rng, max_angle)
    t = rng.uniform(-0.2, 0.2, 3)
    to_scan = np.eye(4)
    to_scan[:3, :3] = R / unit
    to_scan[:3, 3] = t / unit
    scan_v = Vn @ to_scan[:3, :3].T + to_scan[:3, 3]
    lm = {n: landmark_points[i] @ to_scan[:3, :3].T + to_scan[:3, 3] for i, n in enumerate(names)}
    return SyntheticScan(scan_v, Ft, lm, Vt, Ft, warp, to_scan)


def bust_scan(V: np.ndarray, F: np.ndarray, landmarks: dict[str, np.ndarray], seed: int = 0,
              drop_faces: np.ndarray | None = None, unit: float = 1e-3, max_angle: float = 0.5,
              scale: float = 1.08, amplitude: float = 0.006) -> "SyntheticScan":
    """A scanned bust made from a template head (V (n, 3) metres, F (m, 3), landmarks FDP
    name -> (3,) metres): the head warped by template_warp(seed), scaled by `scale` (a
    person larger than the template), its neck set on shoulders and chest (a flattened
    ellipsoid) standing on a cylindrical plinth, the whole turned by up to `max_angle`
    radians and written in `unit` metres. Faces flagged in `drop_faces` (the mouth's
    lining) are left out. truth_vertices / truth_faces are the head alone, in the face
    frame; warp maps template points to their truth (scale included)."""
    rng = np.random.default_rng(seed)
    V = np.asarray(V, dtype=np.float64)
    HV, HF = surface_without(V, F, drop_faces)
    base = template_warp(V, seed + 1000, amplitude, 0.0005)
    centre = 0.5 * (V.min(axis=0) + V.max(axis=0))

    def warp(X):
        return centre + scale * (base(X) - centre)

    W = warp(HV)
    low = W[:, 1].min()
    width = float(np.ptp(W[:, 0]))
    # shoulders and chest: a flattened ellipsoid whose top reaches a little above the neck's end
    chest = trimesh.creation.icosphere(subdivisions=4)
    cv = np.asarray(chest.vertices) * np.array([1.3 * width, 0.45 * width, 0.75 * width])
    cv = cv + np.array([centre[0], low - 0.3 * width, centre[2] - 0.1 * width])
    plinth = trimesh.creation.cylinder(radius=0.6 * width, height=0.5 * width, sections=48)
    pv = np.asarray(plinth.vertices)[:, [0, 2, 1]] + np.array([centre[0], low - 1.0 * width, centre[2]])
    pf = np.asarray(plinth.faces)[:, [0, 2, 1]]  # the y/z swap mirrors: keep the faces outward
    allV = np.vstack([W, cv, pv])
    allF = np.vstack([HF, np.asarray(chest.faces) + len(W), pf + len(W) + len(cv)])
    names = list(landmarks)
    WL = warp(np.array([landmarks[n] for n in names]))
    scan = _scan_of_truth(allV, allF, WL, names, warp, rng, 0.0, max_angle, unit)
    return SyntheticScan(scan.vertices, scan.faces, scan.landmarks, W, HF.astype(np.int32), warp, scan.to_scan)


def template_bust(template, seed: int = 3, V: np.ndarray | None = None) -> SyntheticScan:
    """The bust the suite and the benchmarks make of FaceModel `template`: bust_scan of its
    skin with its skin's feature points, without the mouth's lining (no scanner sees it).
    V (n, 3) metres: the skin to make it of, when not the template's own (an ear moved)."""
    F = np.asarray(template.skin_faces, dtype=np.int64)
    lining = np.asarray(template.skin_region)[F[:, 0]] == template.region_names.index("mouth_cavity")
    fdp = {n: p for n, p in template.feature_point_positions().items() if template.feature_points[n].part == "skin"}
    return bust_scan(template.skin_vertices if V is None else V, F, fdp, seed=seed, drop_faces=lining)


def turned_on_its_neck(template, degrees: float, axis: tuple[float, float, float] = (0.0, 1.0, 0.0)) -> np.ndarray:
    """(n, 3) metres: the skin of FaceModel `template` with its head turned `degrees` about
    `axis` (the head's frame; +y: looking aside) on its neck, as a bust is sculpted: all of
    the turn from 1 cm under the chin (2.1) up, none over the lowest 30 % of the neck below
    it, a smooth step between, about the neck's middle there."""
    from scipy.spatial.transform import Rotation

    V = np.asarray(template.skin_vertices, dtype=np.float64)
    y = V[:, 1]
    top = template.feature_point_positions()["2.1"][1] - 0.01
    bottom = y.min() + 0.3 * (top - y.min())
    t = np.clip((y - bottom) / (top - bottom), 0.0, 1.0)
    share = t * t * (3.0 - 2.0 * t)
    near_bottom = np.abs(y - bottom) < 0.01
    pivot = np.array([np.median(V[near_bottom, 0]), bottom, np.median(V[near_bottom, 2])])
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return Rotation.from_rotvec(np.outer(np.radians(degrees) * share, k)).apply(V - pivot) + pivot
