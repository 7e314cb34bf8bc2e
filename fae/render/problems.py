"""A picture of where a frame's skin breaks: the face, and a close-up, with the skin
vertices that break marked red.

    problem_image(model, skin, bones, problem, pupil_scale=None, size=(480, 480)) -> (H, 2 W, 3) uint8

Both views look at the face as the head holds it (the head's turn taken out, as the skin
check measures): the whole head from the front, and the marked vertices from in front,
turned a little towards where their skin faces, framed to show them with skin around. `fae
verify-skin --pictures` draws one per stream that breaks, at its worst frame.
"""

from __future__ import annotations

import numpy as np

from fae.io.facemodel import FaceModel
from fae.mesh import vertex_normals
from fae.render.framing import CameraView, camera_view, look_at

PROBLEM_RGB = (0.85, 0.02, 0.02)  # linear RGB of the marked vertices
CLOSE_UP_MIN_HALF = 0.012  # m: the close-up shows at least this far either side of the marks
CLOSE_UP_MARGIN = 1.6  # the close-up's half width over the marks' spread (their 90th percentile)
CLOSE_UP_FOV = np.radians(20.0)


def _posed(camera: CameraView, head: np.ndarray) -> CameraView:
    """The camera `camera`, set in the head's own frame, carried along by the head's pose (4, 4)."""
    target = head[:3, :3] @ camera.target + head[:3, 3]
    return CameraView(pose=head @ camera.pose, yfov=camera.yfov, znear=camera.znear, zfar=camera.zfar, target=target)


def close_up_camera(skin_local: np.ndarray, faces: np.ndarray, marked: np.ndarray, aspect: float = 1.0) -> CameraView:
    """A camera (head frame) on the marked vertices `marked` (V,) bool of the skin
    skin_local (V, 3) metres in the head's own frame, faces (F, 3): looking along their mean
    normal tilted well towards the front, from far enough to show CLOSE_UP_MARGIN x their
    spread."""
    P = skin_local[marked]
    centre = P.mean(axis=0)
    spread = float(np.quantile(np.linalg.norm(P - centre, axis=1), 0.9)) if len(P) > 1 else 0.0
    half = max(CLOSE_UP_MIN_HALF, CLOSE_UP_MARGIN * spread) * max(1.0, 1.0 / aspect)
    # (the skin that breaks may face any way, inside the mouth too: seen from in front of
    # the face always, turned towards the side where it faces sideways, as an ear does)
    d = vertex_normals(skin_local, faces)[marked].sum(axis=0)
    d /= max(np.linalg.norm(d), 1e-12)
    n = np.array([0.0, 0.0, 1.5]) + (d if d[2] > -0.2 else 0.0)
    n /= np.linalg.norm(n)
    distance = half / np.tan(0.5 * CLOSE_UP_FOV)
    up = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.95 else np.array([0.0, 0.0, -1.0])
    return CameraView(pose=look_at(centre + distance * n, centre, up=up), yfov=CLOSE_UP_FOV,
                      znear=0.2 * distance, zfar=3.0 * distance, target=centre)


def problem_image(model: FaceModel, skin: np.ndarray, bones: dict[str, np.ndarray], problem: np.ndarray,
                  pupil_scale: dict[str, float] | None = None, size: tuple[int, int] = (480, 480)) -> np.ndarray:
    """(H, 2 W, 3) uint8: the head at a frame (skin (V, 3) metres and bones as played) with
    the vertices `problem` (V,) bool red, whole from the front (left) and close up (right);
    a textured head is drawn in its skin colour (the marks show through no texture)."""
    import dataclasses

    from fae.render.renderer import FaceRenderer, skin_colors

    problem = np.asarray(problem, dtype=bool)
    if not problem.any():
        raise ValueError("problem: no vertex marked; expected at least one")
    head = np.asarray(bones.get("head", np.eye(4)), dtype=np.float64)
    skin = np.asarray(skin, dtype=np.float64)
    local = (skin - head[:3, 3]) @ head[:3, :3]
    rgb = skin_colors(model)
    rgb[problem] = PROBLEM_RGB
    # a texture is drawn over the vertices' colours: the marks would not show through it
    model = dataclasses.replace(model, skin_texture=None)
    aspect = size[0] / size[1]
    cameras = (_posed(camera_view(model, "front", aspect=aspect), head),
               _posed(close_up_camera(local, np.asarray(model.skin_faces, np.int64), problem, aspect), head))
    images = []
    for camera in cameras:
        with FaceRenderer(model, size, camera=camera, supersample=2, skin_rgb=rgb) as renderer:
            images.append(renderer.render(skin, bones, pupil_scale))
    return np.concatenate(images, axis=1)
