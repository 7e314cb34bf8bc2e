"""Face landmarks on any mesh, by looking at it: MediaPipe Face Mesh on a render.

    face_points_seen(model, camera, size) -> FacePoints | None
    landmark_pairs(template, scan_V, scan_F, camera) -> LandmarkPairs

A scan has no feature points, but it has a face a landmark model recognizes once drawn.
The template is drawn and looked at the same way, from the same camera, so the two sets
of MediaPipe's 468 points correspond one to one: each point is cast back onto its mesh
along its pixel's ray, and the detector's own habits (where it puts a contour point on a
given face) cancel out between the two. The pairs drive the fit as feature points do
(fae.adapt.nonrigid), and the MPEG-4 feature points of the scan are then read off the
fitted skin.

MediaPipe 0.10.14 ships its Face Mesh model inside the wheel (nothing is downloaded); it is
an optional dependency (`pip install fae[landmarks]`). Without it, face_points_seen raises
LandmarkModelMissing.

Pairs are kept only where both rays meet their mesh and the point is not on the face's
outline (silhouette points slide with the view); pairs that disagree with a similarity
fitted to all the others (by more than OUTLIER_SHARE of the eye distance and 4 times the
median) are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fae.io.facemodel import FaceModel
from fae.native_stderr import native_stderr_filtered
from fae.render.framing import CameraView

DETECTION_SIZE = (640, 640)
MIN_DETECTION_CONFIDENCE = 0.3
OUTLIER_SHARE = 0.25  # of the template's eye distance
# MediaPipe Face Mesh's face oval (its outline): these points sit on the silhouette.
FACE_OVAL = (10, 338, 297, 332, 284, 251, 389, 356, 454, 323, 361, 288, 397, 365, 379, 378, 400, 377, 152,
             148, 176, 149, 150, 136, 172, 58, 132, 93, 234, 127, 162, 21, 54, 103, 67, 109)
# The eyes' own points (iris excluded): on the template they land on the eyeball, on a
# sculpted scan on its carved eye: usable pairs, but the skin's eyelid does not follow them.
EYE_POINTS = (33, 7, 163, 144, 145, 153, 154, 155, 133, 173, 157, 158, 159, 160, 161, 246,
              263, 249, 390, 373, 374, 380, 381, 382, 362, 398, 384, 385, 386, 387, 388, 466)
# The lips' inner contour: on a closed template mouth its rays slip through the slit into
# the mouth, and on a scan with the mouth shut it is one line.
INNER_LIP_POINTS = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308, 95, 88, 178, 87, 14, 317, 402, 318, 324)


class LandmarkModelMissing(RuntimeError):
    """MediaPipe is not installed."""


@dataclass
class FacePoints:
    """MediaPipe's points seen on a mesh: pixels (468, 2) in an image of `size`, and
    where each lands on the mesh: hit (468,) bool, face (468,) int, bary (468, 3),
    points (468, 3) metres (nan where missed)."""

    pixels: np.ndarray
    size: tuple[int, int]
    hit: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    points: np.ndarray


@dataclass
class LandmarkPairs:
    """Corresponding points of the template's skin and a scan.

    face (k,) int, bary (k, 3): the template skin triangles and barycentric coordinates;
    scan_points (k, 3) metres; index (k,) the MediaPipe index of each pair;
    report: counts, the pairs' residual after a similarity, the detector's verdicts.
    """

    face: np.ndarray
    bary: np.ndarray
    scan_points: np.ndarray
    index: np.ndarray
    report: dict


def surface_model(V: np.ndarray, F: np.ndarray, color=(0.80, 0.78, 0.74, 1.0)) -> FaceModel:
    """A FaceModel holding only a surface V (n, 3) metres, F (m, 3): to draw a scan."""
    V = np.asarray(V, dtype=np.float64)
    n = len(V)
    return FaceModel(skin_vertices=V, skin_faces=np.asarray(F, dtype=np.int32),
                     skin_uv=np.zeros((n, 2), np.float32), skin_color=np.asarray(color, np.float32),
                     skin_mirror=np.arange(n, dtype=np.int32), skin_region=np.zeros(n, np.int32),
                     region_names=["skin"], skin_thickness=np.zeros(n), layer_params={}, parts={},
                     jaw_pivot=np.zeros(3), jaw_axis=np.array([1.0, 0.0, 0.0]), eye_centers={},
                     feature_points={}, muscles=[])


def pixel_rays(camera: CameraView, pixels: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins (k, 3) and unit directions (k, 3), metres, through pixels (k, 2) (x
    right, y down, in an image of `size`) of `camera`."""
    width, height = size
    f = 0.5 * height / np.tan(0.5 * camera.yfov)
    px = np.asarray(pixels, dtype=np.float64)
    d = np.stack([(px[:, 0] - 0.5 * width) / f, -(px[:, 1] - 0.5 * height) / f, -np.ones(len(px))], axis=1)
    d = d @ camera.pose[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.tile(camera.pose[:3, 3], (len(px), 1)), d


def detect_pixels(image: np.ndarray) -> np.ndarray | None:
    """MediaPipe Face Mesh's 468 points (468, 2) in pixels of an RGB image (H, W, 3)
    uint8, or None when it finds no face."""
    points = detect_points(image)
    return None if points is None else points[:, :2]


def _quiet_native_logs() -> None:
    """MediaPipe's C++ log lines are not for users (unless the environment asks for them)."""
    import os

    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")


DRAWING_HELPERS = ("mediapipe.python.solutions.drawing_styles", "mediapipe.python.solutions.drawing_utils")


def preload_landmark_model() -> None:
    """Start importing MediaPipe (half a second, most of it matplotlib, left out) on a thread of its
    own, so that it is there when a caller that reads and searches a scan first needs it.
    Does nothing when MediaPipe is not installed; detect_points reports that."""
    import importlib.util
    import sys
    import threading
    import types

    if importlib.util.find_spec("mediapipe") is None:
        return
    _quiet_native_logs()  # here, not on the thread: the environment is unsafe to change beside threads

    def load():
        # MediaPipe's drawing helpers, which its solutions package imports and fae never
        # uses, import matplotlib.pyplot (0.4 s): placeholders stand in for the two helper
        # modules (nothing else imports them) while MediaPipe loads, and are taken out after
        placeholders = {name: types.ModuleType(name) for name in DRAWING_HELPERS if name not in sys.modules}
        sys.modules.update(placeholders)
        try:
            import mediapipe  # noqa: F401
        except Exception:  # noqa: BLE001 - detect_points imports it again and says what is wrong
            pass
        finally:
            for name, placeholder in placeholders.items():
                if sys.modules.get(name) is placeholder:
                    del sys.modules[name]

    threading.Thread(target=load, name="mediapipe-import", daemon=True).start()


FACE_BOX_SCALE = 2.0  # the crop Face Mesh looks at around a face found by the detector, x its box
SMALL_FACE_SHARE = 0.4  # a face box under this share of the image's shorter side is looked at cropped
TILE_MIN = 256  # pixels: tiles smaller than this are not looked in for a face


def detect_points(image: np.ndarray, small_faces: bool = False) -> np.ndarray | None:
    """MediaPipe Face Mesh's 468 points (468, 3) of an RGB image (H, W, 3) uint8: pixels
    (x right, y down) and the model's own depth (z away from the viewer, in pixels of the
    image's width, 0 about the face's centre), or None when it finds no face.

    Face Mesh's own detector misses a face small in a large frame, or finds it poorly (a
    half-length photo): when it finds none, or first with `small_faces` (a photo), the
    full-range face detector looks for the face, in tiles of the image if need be, and
    Face Mesh looks at FACE_BOX_SCALE x its box."""
    import warnings

    _quiet_native_logs()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import mediapipe as mp
    except ImportError as exc:
        raise LandmarkModelMissing("finding feature points on a scan needs MediaPipe: "
                                   "pip install 'fae[landmarks]' (or give --landmarks)") from exc
    image = np.ascontiguousarray(image[:, :, :3])
    with native_stderr_filtered(), warnings.catch_warnings(), \
            mp.solutions.face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=False,
                                            min_detection_confidence=MIN_DETECTION_CONFIDENCE) as mesh:
        warnings.simplefilter("ignore")  # protobuf deprecation notices from inside MediaPipe
        box = _face_box(mp, image) if small_faces else None
        small = box is not None and max(box[2] - box[0], box[3] - box[1]) < SMALL_FACE_SHARE * min(image.shape[:2])
        points = None if small else _mesh_points(mesh, image, (0, 0))
        if points is None:
            box = box if small_faces else _face_box(mp, image)
            if box is not None:
                x0, y0, x1, y1 = box
                points = _mesh_points(mesh, np.ascontiguousarray(image[y0:y1, x0:x1]), (x0, y0))
        if points is None and small:  # the box was not a face Face Mesh reads: the whole image, as before
            points = _mesh_points(mesh, image, (0, 0))
    return points


def _mesh_points(mesh, image: np.ndarray, offset: tuple[int, int]) -> np.ndarray | None:
    """Face Mesh's 468 points (468, 3) on `image`, in pixels shifted by offset (x, y)."""
    found = mesh.process(image)
    if not found.multi_face_landmarks:
        return None
    h, w = image.shape[:2]
    pts = found.multi_face_landmarks[0].landmark
    return np.array([[p.x * w + offset[0], p.y * h + offset[1], p.z * w] for p in pts[:468]])


def _face_box(mp, image: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) pixels: a square of FACE_BOX_SCALE x the face MediaPipe's
    full-range detector finds most surely, on the whole image or else on overlapping
    tiles of half its size (it looks at 192 pixels: a face of 40 in 1,500 is lost), or None."""
    h, w = image.shape[:2]
    side = min(h, w) // 2
    tiles = [(0, 0, w, h)]
    if side >= TILE_MIN:  # half-overlapping, the last ones flush with the right and bottom edges
        xs = sorted(set(range(0, w - side + 1, side // 2)) | {w - side})
        ys = sorted(set(range(0, h - side + 1, side // 2)) | {h - side})
        tiles += [(x, y, x + side, y + side) for y in ys for x in xs]
    with mp.solutions.face_detection.FaceDetection(model_selection=1,
                                                   min_detection_confidence=MIN_DETECTION_CONFIDENCE) as detector:
        for tx0, ty0, tx1, ty1 in tiles:
            found = detector.process(np.ascontiguousarray(image[ty0:ty1, tx0:tx1]))
            if found.detections:
                break
        else:
            return None
    tw, th = tx1 - tx0, ty1 - ty0
    box = max(found.detections, key=lambda d: d.score[0]).location_data.relative_bounding_box
    cx, cy = tx0 + (box.xmin + box.width / 2) * tw, ty0 + (box.ymin + box.height / 2) * th
    half = FACE_BOX_SCALE * max(box.width * tw, box.height * th) / 2
    x0, y0 = max(int(cx - half), 0), max(int(cy - half), 0)
    x1, y1 = min(int(cx + half), w), min(int(cy + half), h)
    return (x0, y0, x1, y1) if x1 - x0 >= 8 and y1 - y0 >= 8 else None


def face_roll_degrees(points: np.ndarray) -> float:
    """How far the face's eye line is turned from the image's x axis, degrees (0: upright;
    the face's right eye is on the image's left)."""
    right, left = (points[list(e), :2].mean(axis=0) for e in (EYE_POINTS[:16], EYE_POINTS[16:]))
    d = left - right
    return float(np.degrees(np.arctan2(d[1], d[0])))


def detect_points_all_turns(image: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """detect_points on the image in each of its four quarter turns: MediaPipe finds a
    (poorer) face on a photo stored on its side or upside down too, and a false one in a
    turn of an upright photo (upside down, its "chin" above the nose). Returns [(points
    (468, 3) in the image's own pixels, the quarter turns 0-3 of the image they were found
    on)], the face whose eye line lies nearest to level first: most often the real one,
    but a false face can lie more level than a real face's tilt of 10 degrees."""
    h, w = image.shape[:2]
    found = []
    for k in range(4):
        points = detect_points(np.ascontiguousarray(np.rot90(image, k)) if k else image, small_faces=True)
        if points is not None:
            found.append((abs(face_roll_degrees(points)), k, _unturned(points, k, (w, h))))
    return [(points, k) for _, k, points in sorted(found, key=lambda f: (f[0], f[1]))]


def _unturned(points: np.ndarray, quarter_turns: int, size: tuple[int, int]) -> np.ndarray:
    """Points (n, 3) found on np.rot90(image, k) back in the pixels of image (size (w, h))."""
    w, h = size
    out = np.array(points, dtype=np.float64)
    for j in range(quarter_turns, 0, -1):
        # np.rot90 turns counter-clockwise: the pixel (x, y) of np.rot90(image, j) is the
        # pixel (ww - y, x) of np.rot90(image, j - 1), whose width is ww
        ww = w if (j - 1) % 2 == 0 else h
        x, y = out[:, 0].copy(), out[:, 1].copy()
        out[:, 0], out[:, 1] = ww - y, x
    return out


def face_points_seen(model: FaceModel, camera: CameraView, size: tuple[int, int] = DETECTION_SIZE,
                     hit_parts: tuple[str, ...] = ("eye_l", "eye_r")) -> FacePoints | None:
    """Draw `model` from `camera`, find the face's points, and cast each back onto the
    skin (the parts named in `hit_parts` stop a ray too, as the eyes hide the socket);
    None when no face is found."""
    from fae.adapt.query import MeshQuery
    from fae.render.renderer import FaceRenderer

    with FaceRenderer(model, size, camera=camera) as renderer:
        image = renderer.render()
    pixels = detect_pixels(image)
    if pixels is None:
        return None
    V, F = np.asarray(model.skin_vertices, np.float64), np.asarray(model.skin_faces, np.int64)
    allV, allF, base = [V], [F], len(V)
    for name in hit_parts:
        if name in model.parts:
            pv, pf = model.mesh(name)
            allV.append(np.asarray(pv, np.float64))
            allF.append(np.asarray(pf, np.int64) + base)
            base += len(pv)
    q = MeshQuery(np.vstack(allV), np.vstack(allF))
    origins, dirs = pixel_rays(camera, pixels, size)
    hit, t, face, bary = q.ray_hits(origins, dirs, 10.0 * float(np.linalg.norm(camera.pose[:3, 3] - camera.target)))
    hit &= (face >= 0) & (face < len(F))  # on the skin, not on an eye
    points = np.full((len(pixels), 3), np.nan)
    points[hit] = origins[hit] + t[hit, None] * dirs[hit]
    return FacePoints(pixels, size, hit, np.where(hit, face, -1), bary, points)


def landmark_pairs(template: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray, camera: CameraView,
                   size: tuple[int, int] = DETECTION_SIZE, seen: np.ndarray | None = None) -> LandmarkPairs | None:
    """Pairs of template skin points and scan points found by MediaPipe on both (see the
    module docstring); the scan (V (n, 3), F (m, 3)) in the template's face frame, metres;
    seen (n,) bool: the template skin a scanner can see (fae.adapt.transfer.visible_skin).
    None when no face is found on the scan (or on the template)."""
    from fae.adapt.calibration import similarity_transform

    on_template = face_points_seen(template, camera, size)
    if on_template is None:
        return None
    on_scan = face_points_seen(surface_model(scan_V, scan_F), camera, size, hit_parts=())
    if on_scan is None:
        return None
    use = on_template.hit & on_scan.hit
    use[list(FACE_OVAL)] = False
    use[list(EYE_POINTS)] = False
    use[list(INNER_LIP_POINTS)] = False
    if seen is not None:  # template points on skin no scanner sees (inside the mouth) are no use
        use &= seen[np.asarray(template.skin_faces, np.int64)[np.maximum(on_template.face, 0)]].all(axis=1)
    idx = np.flatnonzero(use)
    report = {"detected_on_template": True, "detected_on_scan": True, "points": 468,
              "cast_on_both": int(len(idx))}
    if len(idx) < 20:
        report["pairs"] = int(len(idx))
        return LandmarkPairs(np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), idx, report)
    A, B = on_template.points[idx], on_scan.points[idx]
    s, R, t = similarity_transform(A, B)
    res = np.linalg.norm(s * A @ R.T + t - B, axis=1)
    from fae.adapt.workflow import eye_distance

    good = (res <= OUTLIER_SHARE * eye_distance(template)) | (res <= 4.0 * np.median(res))
    idx = idx[good]
    report.update({"pairs": int(len(idx)), "similarity_scale": float(s),
                   "similarity_residual_m": float(np.sqrt(np.mean(res[good] ** 2))),
                   "dropped_as_outliers": int((~good).sum())})
    return LandmarkPairs(on_template.face[idx], on_template.bary[idx], on_scan.points[idx], idx, report)


# Each eye's own points (the first half of EYE_POINTS is the face's right eye).
EYES = (EYE_POINTS[:16], EYE_POINTS[16:])


def template_points(template: FaceModel, size: tuple[int, int] = DETECTION_SIZE):
    """The landmark model's points on a front render of `template`, with the template's
    feature points seen in the same render (fae.adapt.photo.TemplatePoints); None when no
    face is found on it."""
    from fae.adapt.photo import TemplatePoints
    from fae.render.framing import camera_view

    camera = camera_view(template, "front", aspect=size[0] / size[1])
    seen = face_points_seen(template, camera, size)
    if seen is None:
        return None
    fdp = {n: p for n, p in template.feature_point_positions().items() if template.feature_points[n].part == "skin"}
    names = sorted(fdp)
    pixels = camera.project(np.array([fdp[n] for n in names]), size)
    return TemplatePoints(pixels=seen.pixels, points=seen.points, fdp_pixels=dict(zip(names, pixels)))
# The lips' inner contour as a polygon (upper lip left to right, lower lip back): the mouth's opening.
MOUTH_OPENING = INNER_LIP_POINTS[:11] + INNER_LIP_POINTS[11:][::-1]
# The lips' outer contour but its corners (61, 291): on a photo of a smile or an open mouth
# they would open the neutral head's mouth.
OUTER_LIP_POINTS = (146, 91, 181, 84, 17, 314, 405, 321, 375, 185, 40, 39, 37, 0, 267, 269, 270, 409)


def points_on_render(model: FaceModel, size: tuple[int, int]) -> np.ndarray | None:
    """The landmark model's points (468, 3) on `model` drawn through the camera of the
    photo it was adapted from (its scan_transform; fae.render.framing.photo_camera), in
    the photo's pixels; None when the model finds no face there. Rendered at least
    DETECTION_SIZE large (a small photo's face is drawn larger, then scaled back)."""
    from fae.render.framing import photo_camera
    from fae.render.renderer import FaceRenderer

    width, height = size
    k = max(1.0, DETECTION_SIZE[0] / max(width, height))
    render_size = (round(width * k), round(height * k))
    with FaceRenderer(model, render_size, camera=photo_camera(model.scan_transform, size), supersample=2) as r:
        image = r.render()
    points = detect_points(image, small_faces=True)  # looked at as the photo was
    return None if points is None else points / k
