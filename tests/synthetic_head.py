"""A small but complete FaceModel for tests: every field populated with plausible values.

An ellipsoidal skin (icosphere, mirror-symmetric), a cranium inside it, mandible, teeth,
tongue and two eyeballs with vertex colours, all 84 MPEG-4 feature points placed on the
skin where a face has them (so the FAPU come out face-like), linear and sphincter
muscles, two FaceDefTables and a calibrated-looking fap_mapping of assorted dtypes.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from fae.io.facemodel import PART_BONES, FaceDefTable, FaceModel, Muscle, Part, SurfacePoint
from fae.mpeg4 import FEATURE_POINTS

REGION_NAMES = ["scalp", "forehead", "eyes", "cheek", "lip_upper", "lip_lower", "chin"]

# Rough neutral-face positions (metres, face frame) of the points the FAPU depend on and
# of a few landmarks; the remaining feature points are spread over the face front.
FDP_TARGETS = {
    "3.1": (0.032, 0.036, 0.09), "3.2": (-0.032, 0.036, 0.09),
    "3.3": (0.032, 0.024, 0.09), "3.4": (-0.032, 0.024, 0.09),
    "3.5": (0.032, 0.030, 0.09), "3.6": (-0.032, 0.030, 0.09),
    "9.15": (0.0, -0.012, 0.11), "2.2": (0.0, -0.032, 0.1),
    "2.3": (0.0, -0.036, 0.1), "8.3": (0.026, -0.034, 0.1), "8.4": (-0.026, -0.034, 0.1),
    "2.1": (0.0, -0.075, 0.08), "9.3": (0.0, 0.0, 0.12),
}


def fdp_names_from_group_sizes() -> list[str]:
    """The 84 MPEG-4 feature point names, from the standard's group sizes."""
    sizes = {2: 14, 3: 14, 4: 6, 5: 4, 6: 4, 7: 1, 8: 10, 9: 15, 10: 10, 11: 6}
    return [f"{g}.{i}" for g, n in sizes.items() for i in range(1, n + 1)]


def _mesh(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32)


def _surface_points(part: str, vertices: np.ndarray, faces: np.ndarray, targets) -> list[SurfacePoint]:
    """The points of mesh `part` closest to each of `targets` (k, 3)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    closest, _, triangles = trimesh.proximity.closest_point(mesh, np.asarray(targets, dtype=np.float64))
    bary = trimesh.triangles.points_to_barycentric(vertices[faces[triangles]], closest)
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return [SurfacePoint(part=part, triangle=int(t), bary=b.copy()) for t, b in zip(triangles, bary)]


def _surface_point(part: str, vertices: np.ndarray, faces: np.ndarray, target) -> SurfacePoint:
    return _surface_points(part, vertices, faces, [target])[0]


def _mirror_index(vertices: np.ndarray) -> np.ndarray:
    distance, index = cKDTree(vertices).query(vertices * (-1.0, 1.0, 1.0))
    assert distance.max() < 1e-9, "the synthetic skin must be mirror-symmetric"
    return index.astype(np.int32)


def synthetic_head(personalized: bool = True) -> FaceModel:
    """A complete FaceModel of about 650 skin vertices (deterministic)."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    skin_v, skin_f = _mesh(sphere)
    skin_v = skin_v * (0.075, 0.11, 0.095)
    x, y, z = skin_v.T

    uv = np.stack([0.5 + np.arctan2(x, z) / (2 * np.pi), 0.5 + np.arcsin(np.clip(y / 0.11, -1, 1)) / np.pi], axis=1)
    region = np.select(
        [y > 0.07, y > 0.045, y > 0.015, y > -0.025, y > -0.034, y > -0.05],
        [0, 1, 2, 3, 4, 5],
        default=6,
    ).astype(np.int32)
    region[(z < 0) & (y > 0.0)] = 0
    thickness = np.where(z > 0, 0.006, 0.004) + 0.002 * (np.abs(y) < 0.04)

    parts: dict[str, Part] = {}

    def add(name: str, mesh: trimesh.Trimesh, color, vertex_colors=None) -> None:
        v, f = _mesh(mesh)
        parts[name] = Part(v, f, np.asarray(color, dtype=np.float32), PART_BONES[name], vertex_colors)

    bone = (0.93, 0.89, 0.80, 1.0)
    cranium = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    cranium.apply_scale((0.068, 0.1, 0.085))
    add("cranium", cranium, bone)
    mandible = trimesh.creation.box(extents=(0.09, 0.03, 0.07))
    mandible.apply_translation((0.0, -0.06, 0.035))
    add("mandible", mandible, bone)
    for name, yy in (("upper_teeth", -0.028), ("lower_teeth", -0.04)):
        teeth = trimesh.creation.box(extents=(0.04, 0.01, 0.012))
        teeth.apply_translation((0.0, yy, 0.08))
        add(name, teeth, (0.95, 0.93, 0.88, 1.0))
    tongue = trimesh.creation.box(extents=(0.035, 0.008, 0.05))
    tongue.apply_translation((0.0, -0.036, 0.055))
    add("tongue", tongue, (0.75, 0.3, 0.3, 1.0))
    eye_centers = {}
    for name, side in (("eye_l", 1.0), ("eye_r", -1.0)):
        centre = np.array([side * 0.032, 0.03, 0.072])
        eye = trimesh.creation.icosphere(subdivisions=2, radius=0.012)
        iris = eye.vertices[:, 2] > 0.009
        colors = np.where(iris[:, None], (0.25, 0.15, 0.08, 1.0), (0.95, 0.95, 0.93, 1.0)).astype(np.float32)
        eye.apply_translation(centre)
        add(name, eye, (0.95, 0.95, 0.93, 1.0), colors)
        eye_centers[name] = centre

    targets = []
    for point in FEATURE_POINTS:
        target = FDP_TARGETS.get(point.name)
        if target is None:
            spread = 0.012 * ((point.index - 1) % 4) + 0.005
            target = (point.side * spread, 0.08 - 0.012 * (point.group - 2), 0.12)
        targets.append(target)
    points = _surface_points("skin", skin_v, skin_f, targets)
    feature_points = {point.name: sp for point, sp in zip(FEATURE_POINTS, points)}

    cv, cf = parts["cranium"].vertices, parts["cranium"].faces
    muscles = []
    for side, suffix in ((1.0, "l"), (-1.0, "r")):
        muscles.append(
            Muscle(
                name=f"zygomatic_major_{suffix}",
                kind="linear",
                attachment=_surface_point("cranium", cv, cf, (side * 0.06, 0.0, 0.06)),
                insertion=_surface_point("skin", skin_v, skin_f, (side * 0.026, -0.034, 0.1)),
                regions=["cheek", "lip_upper"],
                zone_angle=0.5,
                fall_start=0.012,
                fall_end=0.035,
            )
        )
    muscles.append(
        Muscle(
            name="orbicularis_oris",
            kind="sphincter",
            attachment=_surface_point("skin", skin_v, skin_f, (0.0, -0.034, 0.1)),
            insertion=None,
            regions=["lip_upper", "lip_lower"],
            semi_axes=np.array([0.03, 0.015]),
            axes=np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
        )
    )

    chin = np.argsort(np.linalg.norm(skin_v - (0.0, -0.075, 0.08), axis=1))[:5].astype(np.int32)
    brow = np.argsort(np.linalg.norm(skin_v - (0.03, 0.05, 0.08), axis=1))[:4].astype(np.int32)
    tables = [
        FaceDefTable(3, "skin", chin, np.array([0.0, 2048.0]), np.tile([0.0, -1.0e-5, 0.0], (1, 5, 1))),
        FaceDefTable(
            31,
            "skin",
            brow,
            np.array([-1024.0, 0.0, 512.0, 2048.0]),
            np.linspace(0.0, 2e-5, 3 * 4 * 3).reshape(3, 4, 3),
        ),
    ]

    rng = np.random.default_rng(7)
    fap_mapping = {
        "muscle_gain": rng.normal(size=(68, 3)),
        "muscle_index": np.array([0, 1, 2, -1], dtype=np.int16),
        "active": rng.random((2, 3)) > 0.5,
        "jaw_gain": np.array(1.5e-4, dtype=np.float32),
    }
    scan = np.eye(4)
    if personalized:
        scan = np.diag([1000.0, 1000.0, 1000.0, 1.0])
        scan[:3, 3] = (12.5, -40.0, 3.25)

    return FaceModel(
        skin_vertices=skin_v,
        skin_faces=skin_f,
        skin_uv=np.clip(uv, 0.0, 1.0).astype(np.float32),
        skin_color=np.array([0.80, 0.57, 0.46, 1.0], dtype=np.float32),
        skin_mirror=_mirror_index(skin_v),
        skin_region=region,
        region_names=list(REGION_NAMES),
        skin_thickness=thickness,
        layer_params={"layer_depths": [0.0, 0.0025, 0.006], "spring_stiffness": 150.0, "layer_count": 3, "note": None},
        parts=parts,
        jaw_pivot=np.array([0.0, -0.02, 0.01]),
        jaw_axis=np.array([1.0, 0.0, 0.0]),
        eye_centers=eye_centers,
        feature_points=feature_points,
        muscles=muscles,
        face_def_tables=tables,
        fap_mapping=fap_mapping,
        scan_transform=scan,
        meta={"name": "synthetic head", "generator": "tests/synthetic_head.py", "tags": ["test", "synthetic"]},
    )
