"""Camera presets framed from a head's own feature points (no OpenGL here).

The face looks along +Z, y is up, its own left is +x. A view is a rotation of the camera
about the vertical axis through the head's centre: "front" looks at the face,
"three-quarter" from 35 degrees towards the face's left, "profile" from its left (+x).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fae.anatomy.surface_points import chin_contour_point
from fae.io.facemodel import FaceModel

VIEWS = {"front": 0.0, "three-quarter": np.radians(35.0), "profile": np.radians(90.0)}

# Proportions of an adult head relative to its height (chin 2.1 to top of skull 11.4),
# used where a head lacks the feature point that would measure them.
_HEAD_WIDTH_PER_ES = 2.4  # head width / eye separation ES0
_HEAD_DEPTH_PER_HEIGHT = 0.85  # nose tip to back of skull / head height
_PIVOT_BEHIND_EYES_PER_ES = 1.2  # centre of the skull behind the pupils / ES0


# The largest side, in pixels, of an image drawn in one pass (OSMesa's viewport: past it the
# picture was cut to 16384 px without an error, the head squashed; at 65536 the process died)
MAX_RENDER_SIDE = 16384

@dataclass
class CameraView:
    """A perspective camera looking at the head.

    pose    (4, 4) float64 camera-to-world transform (OpenGL convention: looks along -z)
    yfov    vertical field of view, radians
    znear, zfar  clipping distances, metres
    target  (3,) metres, the point the camera looks at (image centre)
    """

    pose: np.ndarray
    yfov: float
    znear: float
    zfar: float
    target: np.ndarray

    def project(self, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """(n, 2) float64 pixel coordinates (x right, y down, pixel centres at +0.5) of
        world points (n, 3) metres in an image of `size` (width, height)."""
        width, height = size
        P = np.atleast_2d(np.asarray(points, dtype=np.float64))
        world_to_cam = np.linalg.inv(self.pose)
        c = P @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
        f = 0.5 * height / np.tan(0.5 * self.yfov)
        x = 0.5 * width + f * c[:, 0] / -c[:, 2]
        y = 0.5 * height - f * c[:, 1] / -c[:, 2]
        return np.stack([x, y], axis=1)


@dataclass
class HeadFrame:
    """Measurements of a head that framing needs, in metres.

    centre  (3,): horizontal centre between the pupils, vertically half-way from chin to
            top of skull, in depth the centre of the skull
    height  chin (2.1) to top of skull (11.4)
    width   head width seen from the front
    depth   nose tip to back of skull
    """

    centre: np.ndarray
    height: float
    width: float
    depth: float


def head_frame(model: FaceModel) -> HeadFrame:
    """Measure the head from its feature points, falling back to the skin's bounding box.

    Uses pupils 3.5/3.6 (else `eye_centers`) for the horizontal centre and ES0, chin 2.1
    and top of skull 11.4 (else hairline 11.1, else the bounding box) for the height.
    """
    V = np.asarray(model.skin_vertices, dtype=np.float64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    fp = {}
    for name in ("3.5", "3.6", "2.1", "11.4", "11.1", "9.3", "11.6"):
        point = model.feature_points.get(name)
        if point is not None:
            try:
                fp[name] = model.surface_point_position(point)
            except (KeyError, IndexError):
                pass
    if "3.5" in fp and "3.6" in fp:
        eyes = (fp["3.5"], fp["3.6"])
    elif len(model.eye_centers) >= 2:
        eyes = tuple(np.asarray(c, dtype=np.float64) for c in list(model.eye_centers.values())[:2])
    else:
        eyes = None
    if eyes is not None:
        es0 = float(np.linalg.norm(eyes[0] - eyes[1]))
        eye_mid = 0.5 * (eyes[0] + eyes[1])
    else:
        es0 = float(hi[0] - lo[0]) / _HEAD_WIDTH_PER_ES
        eye_mid = np.array([0.5 * (lo[0] + hi[0]), lo[1] + 0.6 * (hi[1] - lo[1]), hi[2]])
    if es0 <= 0.0:
        es0 = float(hi[0] - lo[0]) / _HEAD_WIDTH_PER_ES
    chin = chin_contour_point(model)[1] if "2.1" in fp else lo[1]
    if "11.4" in fp:
        top = fp["11.4"][1]
    elif "11.1" in fp:
        top = fp["11.1"][1] + 0.25 * (fp["11.1"][1] - chin)
    else:
        top = hi[1]
    height = float(top - chin) if top > chin else float(hi[1] - lo[1])
    width = min(_HEAD_WIDTH_PER_ES * es0, float(hi[0] - lo[0]))
    if "9.3" in fp and "11.6" in fp:
        depth = float(fp["9.3"][2] - fp["11.6"][2])
    else:
        depth = min(_HEAD_DEPTH_PER_HEIGHT * height, float(hi[2] - lo[2]))
    centre = np.array([eye_mid[0], 0.5 * (top + chin), eye_mid[2] - _PIVOT_BEHIND_EYES_PER_ES * es0])
    return HeadFrame(centre=centre, height=height, width=max(width, 1e-6), depth=max(depth, 1e-6))


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(4, 4) camera-to-world pose at `eye` looking at `target` (camera -z towards it)."""
    eye = np.asarray(eye, dtype=np.float64)
    back = eye - np.asarray(target, dtype=np.float64)
    back /= np.linalg.norm(back)
    right = np.cross(np.asarray(up, dtype=np.float64), back)
    if np.linalg.norm(right) < 1e-9:
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up_true = np.cross(back, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up_true, back, eye
    return pose


def camera_view(model: FaceModel, view: str = "front", aspect: float = 4.0 / 3.0,
                yfov: float = np.radians(20.0), margin: float = 1.25) -> CameraView:
    """Frame the whole head in a `view` preset (see VIEWS) for an image of width/height `aspect`.

    The head (height, and its width or depth as seen from this side) fills 1/`margin` of
    the image; the camera stands far enough that the nearest part of the head fits too.
    """
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r}: expected one of {', '.join(VIEWS)}")
    frame = head_frame(model)
    yaw = VIEWS[view]
    seen_width = abs(np.cos(yaw)) * frame.width + abs(np.sin(yaw)) * frame.depth
    seen_depth = abs(np.sin(yaw)) * frame.width + abs(np.cos(yaw)) * frame.depth
    tan_y = np.tan(0.5 * yfov)
    tan_x = tan_y * aspect
    distance = max(0.5 * margin * frame.height / tan_y, 0.5 * margin * seen_width / tan_x) + 0.5 * seen_depth
    direction = np.array([np.sin(yaw), 0.0, np.cos(yaw)])
    pose = look_at(frame.centre + distance * direction, frame.centre)
    extent = max(frame.height, frame.depth, frame.width)
    return CameraView(pose=pose, yfov=float(yfov), znear=max(distance - 2.0 * extent, 0.05 * distance),
                      zfar=distance + 2.0 * extent, target=frame.centre)


PHOTO_CAMERA_DISTANCE = 30.0  # metres: far enough that perspective is within 1 % of the photo's weak perspective


def photo_camera(to_photo: np.ndarray, size: tuple[int, int]) -> CameraView:
    """The camera of a photo whose pixels a head's face frame maps to: to_photo (4, 4) a
    similarity, face frame (metres) -> photo pixels (x right, y down, z away; the
    scan_transform of a head adapted from a photo, fae.adapt.photo); size (width, height)
    of the photo. The camera stands PHOTO_CAMERA_DISTANCE away with the field of view
    that keeps the photo's scale (nearly orthographic), so a render of the head at `size`
    lies over the photo."""
    A = np.asarray(to_photo, dtype=np.float64)[:3, :3]
    s = float(np.cbrt(abs(np.linalg.det(A))))  # pixels per metre
    R = np.diag([1.0, -1.0, -1.0]) @ A / s  # face frame -> camera axes (x right, y up, z towards the viewer)
    width, height = size
    centre = np.linalg.solve(np.asarray(to_photo)[:3, :3], np.array([0.5 * width, 0.5 * height, 0.0]) - to_photo[:3, 3])
    # the image centre's point of the face's depth plane (z = 0 in photo pixels, the face's middle)
    pose = np.eye(4)
    pose[:3, :3] = R.T
    pose[:3, 3] = centre + PHOTO_CAMERA_DISTANCE * R.T[:, 2]
    yfov = 2.0 * np.arctan(0.5 * height / (s * PHOTO_CAMERA_DISTANCE))
    return CameraView(pose=pose, yfov=float(yfov), znear=PHOTO_CAMERA_DISTANCE - 1.0,
                      zfar=PHOTO_CAMERA_DISTANCE + 1.0, target=centre)
