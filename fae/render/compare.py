"""A picture that tells whether to trust an adapted head: the scan beside the head, and
the two overlaid, front and profile.

    comparison_image(model, scan_V, scan_F, keep, size) -> (H, W, 3) uint8

Everything is drawn in the head's face frame (the scan mapped into it by the inverse of
the head's scan_transform, a similarity: the picture is the scan's own frame, turned to
face the camera). Columns: the scan, with the part fae fitted in stone colour and the
part it left out (plinth, shoulders) in blue; the adapted head; both at once, where
whichever surface is nearer the camera shows: skin colour where the head stands out of
the scan, stone where the scan stands out of the head. Rows: front, profile.
"""

from __future__ import annotations

import numpy as np

from fae.io.facemodel import FaceModel, Part
from fae.render.framing import camera_view
from fae.render.landmarks import surface_model

SCAN_COLOR = (0.80, 0.78, 0.74, 1.0)
LEFT_OUT_COLOR = (0.35, 0.45, 0.75, 1.0)
HEAD_COLOR = (0.85, 0.55, 0.45, 1.0)


def _faces_of(F: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    inside = keep[F].all(axis=1)
    return F[inside], F[~inside]


def comparison_image(model: FaceModel, scan_V: np.ndarray, scan_F: np.ndarray, keep: np.ndarray,
                     size: tuple[int, int] = (360, 360)) -> np.ndarray:
    """(2 H, 3 W, 3) uint8: see the module docstring. scan_V (n, 3) in the scan's frame and
    unit, scan_F (m, 3), keep (n,) bool the head part."""
    from fae.render.renderer import FaceRenderer

    S_inv = np.linalg.inv(model.scan_transform)
    V = np.asarray(scan_V, np.float64) @ S_inv[:3, :3].T + S_inv[:3, 3]
    F = np.asarray(scan_F, np.int64)
    head_F, rest_F = _faces_of(F, np.asarray(keep, bool))
    scan = surface_model(V, head_F, SCAN_COLOR)
    if len(rest_F):
        scan.parts["left_out"] = Part(V, rest_F.astype(np.int32), np.asarray(LEFT_OUT_COLOR, np.float32), "head")
    both = surface_model(V, head_F, SCAN_COLOR)
    both.parts["head"] = Part(model.skin_vertices, np.asarray(model.skin_faces, np.int32),
                              np.asarray(HEAD_COLOR, np.float32), "head")
    rows = []
    for view in ("front", "profile"):
        camera = camera_view(model, view, aspect=size[0] / size[1], margin=1.6)
        images = []
        for m in (scan, model, both):
            with FaceRenderer(m, size, view, camera=camera, supersample=2) as renderer:
                images.append(renderer.render())
        rows.append(np.concatenate(images, axis=1))
    return np.concatenate(rows, axis=0)


def photo_comparison_image(model: FaceModel, image: np.ndarray, height: int = 360) -> np.ndarray:
    """(height, 4 height, 3) uint8 for a head adapted from a photo: the photo around the
    face, the head drawn through the photo's camera (fae.render.framing.photo_camera)
    over the same square, the two blended half and half, and the head in profile.
    image (h, w, 3) uint8, the photo."""
    from PIL import Image

    from fae.render.framing import photo_camera
    from fae.render.renderer import FaceRenderer

    M = np.asarray(model.scan_transform, dtype=np.float64)
    xy = (model.skin_vertices @ M[:3, :3].T + M[:3, 3])[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    side = 1.15 * float(max(hi - lo))
    x0, y0 = 0.5 * (lo + hi) - 0.5 * side  # the square around the head, photo pixels
    k = height / side
    to_crop = np.diag([k, k, k, 1.0]) @ np.array([[1, 0, 0, -x0], [0, 1, 0, -y0], [0, 0, 1, 0], [0, 0, 0, 1.0]]) @ M
    with FaceRenderer(model, (height, height), camera=photo_camera(to_crop, (height, height)),
                      supersample=2) as renderer:
        head = renderer.render()
    with FaceRenderer(model, (height, height), "profile", supersample=2) as renderer:
        profile = renderer.render()
    # the square may reach past the photo's edges (a tight portrait): cropped with a margin
    # of black, then scaled
    box = tuple(int(round(v)) for v in (x0, y0, x0 + side, y0 + side))
    photo = np.asarray(Image.fromarray(np.ascontiguousarray(image[:, :, :3])).crop(box).resize(
        (height, height), Image.LANCZOS))
    blend = ((photo.astype(np.uint16) + head) // 2).astype(np.uint8)
    return np.concatenate([photo, head, blend, profile], axis=1)
