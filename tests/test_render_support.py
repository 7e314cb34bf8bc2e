"""A synthetic head and jaw-opening frames for the render/video/play tests.

The head is built in memory so that these tests do not depend on the shipped template:
an ellipsoidal skin (20k triangles) with a mouth slit, eyeballs with iris and pupil vertex
colours, a cranium sphere, a mandible box, teeth and a tongue. `jaw_frames` yields frames
shaped like `fae.animate.player.PlayedFrame`: the lower face and the jaw-borne parts turn
about the jaw hinge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from fae.io.facemodel import FaceModel, Part, SurfacePoint
from fae.mpeg4.fdps import FEATURE_POINTS

SEMI_AXES = np.array([0.075, 0.115, 0.095])  # skin ellipsoid, metres
MOUTH_Y = -0.055
JAW_PIVOT = np.array([0.0, -0.03, -0.02])
EYE_RADIUS = 0.012


def _box(extents, centre):
    m = trimesh.creation.box(extents=extents)
    return np.asarray(m.vertices) + centre, np.asarray(m.faces, dtype=np.int32)


def _point_on(vertices, faces, part, target):
    """SurfacePoint at the vertex nearest `target` (barycentric one-hot on a triangle using it)."""
    v = int(np.argmin(np.linalg.norm(vertices - target, axis=1)))
    tri = int(np.nonzero((faces == v).any(axis=1))[0][0])
    bary = (faces[tri] == v).astype(np.float64)
    return SurfacePoint(part=part, triangle=tri, bary=bary)


def synthetic_head(subdivisions: int = 5) -> FaceModel:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    V = np.asarray(sphere.vertices) * SEMI_AXES
    F = np.asarray(sphere.faces, dtype=np.int32)
    c = V[F].mean(axis=1)
    mouth = (c[:, 2] > 0.03) & ((c[:, 0] / 0.026) ** 2 + ((c[:, 1] - MOUTH_Y) / 0.0045) ** 2 < 1.0)
    F = F[~mouth]
    used = np.unique(F)
    remap = -np.ones(len(V), dtype=np.int64)
    remap[used] = np.arange(len(used))
    V, F = V[used], remap[F].astype(np.int32)

    parts = {}
    eye_centers = {}
    for name, sx in (("eye_l", 1.0), ("eye_r", -1.0)):
        x, y = 0.032 * sx, 0.02
        zs = SEMI_AXES[2] * np.sqrt(1 - (x / SEMI_AXES[0]) ** 2 - (y / SEMI_AXES[1]) ** 2)
        centre = np.array([x, y, zs + 0.004 - EYE_RADIUS])
        eye = trimesh.creation.icosphere(subdivisions=3, radius=EYE_RADIUS)
        ev = np.asarray(eye.vertices)
        cosang = ev[:, 2] / EYE_RADIUS
        colors = np.tile(np.array([0.85, 0.83, 0.80, 1.0], dtype=np.float32), (len(ev), 1))
        colors[cosang > np.cos(np.radians(38))] = (0.10, 0.22, 0.42, 1.0)
        colors[cosang > np.cos(np.radians(16))] = (0.01, 0.01, 0.01, 1.0)
        parts[name] = Part(vertices=ev + centre, faces=np.asarray(eye.faces, dtype=np.int32),
                           color=np.array([0.85, 0.83, 0.8, 1.0], dtype=np.float32), bone=name,
                           vertex_colors=colors)
        eye_centers[name] = centre
    cran = trimesh.creation.icosphere(subdivisions=3, radius=0.065)
    parts["cranium"] = Part(np.asarray(cran.vertices) + [0, 0.02, -0.005], np.asarray(cran.faces, dtype=np.int32),
                            np.array([0.9, 0.85, 0.75, 1], dtype=np.float32), "head")
    specs = {
        "mandible": ((0.05, 0.012, 0.05), (0.0, -0.08, 0.02), (0.9, 0.85, 0.75, 1), "jaw"),
        "upper_teeth": ((0.036, 0.008, 0.010), (0.0, MOUTH_Y + 0.0045, 0.074), (0.92, 0.9, 0.82, 1), "head"),
        "lower_teeth": ((0.034, 0.008, 0.010), (0.0, MOUTH_Y - 0.0055, 0.072), (0.92, 0.9, 0.82, 1), "jaw"),
        "tongue": ((0.03, 0.008, 0.045), (0.0, MOUTH_Y - 0.011, 0.045), (0.55, 0.14, 0.15, 1), "tongue"),
    }
    for name, (ext, centre, color, bone) in specs.items():
        pv, pf = _box(ext, np.array(centre))
        parts[name] = Part(pv, pf, np.array(color, dtype=np.float32), bone)

    fp = {
        "2.1": _point_on(V, F, "skin", np.array([0.0, -SEMI_AXES[1], 0.02])),
        "11.4": _point_on(V, F, "skin", np.array([0.0, SEMI_AXES[1], 0.0])),
        "11.6": _point_on(V, F, "skin", np.array([0.0, 0.0, -SEMI_AXES[2]])),
        "9.3": _point_on(V, F, "skin", np.array([0.0, -0.01, SEMI_AXES[2]])),
        "2.2": _point_on(V, F, "skin", np.array([0.0, MOUTH_Y + 0.005, 0.09])),
        "2.3": _point_on(V, F, "skin", np.array([0.0, MOUTH_Y - 0.005, 0.09])),
    }
    for name, fdp in (("eye_l", "3.5"), ("eye_r", "3.6")):
        p = parts[name]
        fp[fdp] = _point_on(p.vertices, p.faces, name, eye_centers[name] + [0, 0, EYE_RADIUS])
    # The points framing does not use: on the skin, spread over the front of the face.
    for k, point in enumerate(FEATURE_POINTS):
        if point.name not in fp:
            angle = 2.0 * np.pi * k / len(FEATURE_POINTS)
            fp[point.name] = _point_on(V, F, "skin", np.array([0.04 * np.cos(angle), 0.05 * np.sin(angle), 0.09]))
    n = len(V)
    return FaceModel(
        skin_vertices=V, skin_faces=F, skin_uv=np.zeros((n, 2), dtype=np.float32),
        skin_color=np.array([0.80, 0.55, 0.45, 1.0], dtype=np.float32),
        skin_mirror=np.arange(n, dtype=np.int32), skin_region=np.zeros(n, dtype=np.int32),
        region_names=["face"], skin_thickness=np.full(n, 0.01), layer_params={}, parts=parts,
        jaw_pivot=JAW_PIVOT.copy(), jaw_axis=np.array([1.0, 0.0, 0.0]), eye_centers=eye_centers,
        feature_points=fp, muscles=[], meta={"name": "synthetic test head"},
    )


def jaw_transform(angle: float) -> np.ndarray:
    """(4, 4) rotation by `angle` radians about the jaw hinge (+x through JAW_PIVOT); > 0 opens."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = JAW_PIVOT - R @ JAW_PIVOT
    return T


@dataclass
class JawFrame:
    """Same fields as fae.animate.player.PlayedFrame."""

    index: int
    time: float
    skin_vertices: np.ndarray
    bone_transforms: dict


def jaw_frames(model: FaceModel, angles, fps: float = 25.0):
    """Frames opening the jaw by each of `angles` (radians): lower-face skin and jaw parts turn."""
    V = model.skin_vertices
    below = np.clip((MOUTH_Y - V[:, 1]) / 0.004, 0.0, 1.0) * np.clip(V[:, 2] / 0.03, 0.0, 1.0)
    for i, a in enumerate(angles):
        T = jaw_transform(a)
        moved = V @ T[:3, :3].T + T[:3, 3]
        skin = V + below[:, None] * (moved - V)
        yield JawFrame(i, i / fps, skin, {"head": np.eye(4), "jaw": T, "tongue": T,
                                          "eye_l": np.eye(4), "eye_r": np.eye(4)})
