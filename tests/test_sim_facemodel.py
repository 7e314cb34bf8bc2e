"""A small anatomical FaceModel built from ellipsoids, for the runtime's tests and benchmark
(while no shipped head is at hand): skin, skull and mandible, teeth, tongue, eyes, the
FAP-bound feature points, regions and a set of Waters muscles."""

from __future__ import annotations

import numpy as np
import trimesh

from fae.io.facemodel import FaceModel, Muscle, Part, SurfacePoint

SEMI = np.array([0.078, 0.112, 0.098])
THICKNESS = 0.012
EYE_CENTERS = {"eye_l": np.array([0.032, 0.028, 0.066]), "eye_r": np.array([-0.032, 0.028, 0.066])}
EYE_RADIUS = 0.012

# (azimuth from +z towards +x, elevation) on the skin ellipsoid, radians
FDP_DIRECTIONS = {
    "2.1": (0.0, -0.62), "2.2": (0.0, -0.262), "2.3": (0.0, -0.298), "2.4": (0.27, -0.28), "2.5": (-0.27, -0.28),
    "2.6": (0.14, -0.265), "2.7": (-0.14, -0.265), "2.8": (0.14, -0.295), "2.9": (-0.14, -0.295),
    "2.10": (0.0, -0.48), "2.11": (0.25, -0.52), "2.12": (-0.25, -0.52), "2.13": (0.95, -0.42), "2.14": (-0.95, -0.42),
    "3.1": (0.33, 0.165), "3.2": (-0.33, 0.165), "3.3": (0.33, 0.075), "3.4": (-0.33, 0.075),
    "3.7": (0.50, 0.12), "3.8": (-0.17, 0.12), "3.11": (0.17, 0.12), "3.12": (-0.50, 0.12),
    "4.1": (0.12, 0.26), "4.2": (-0.12, 0.26), "4.3": (0.33, 0.29), "4.4": (-0.33, 0.29),
    "4.5": (0.52, 0.25), "4.6": (-0.52, 0.25),
    "5.1": (0.45, -0.16), "5.2": (-0.45, -0.16), "5.3": (0.55, -0.02), "5.4": (-0.55, -0.02),
    "8.1": (0.0, -0.228), "8.2": (0.0, -0.335), "8.3": (0.30, -0.28), "8.4": (-0.30, -0.28),
    "8.5": (0.15, -0.24), "8.6": (-0.15, -0.24), "8.7": (0.15, -0.32), "8.8": (-0.15, -0.32),
    "9.1": (0.08, -0.10), "9.2": (-0.08, -0.10), "9.3": (0.0, -0.03), "9.15": (0.0, -0.12),
    "10.1": (1.45, 0.14), "10.2": (-1.45, 0.14), "10.3": (1.65, 0.03), "10.4": (-1.65, 0.03),
    "11.1": (0.0, 0.62),
}


def _dir(az: float, el: float) -> np.ndarray:
    return np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])


def _on_ellipsoid(d: np.ndarray, semi: np.ndarray) -> np.ndarray:
    return d / np.sqrt(np.sum((d / semi) ** 2))


def _surface_point(mesh: trimesh.Trimesh, part: str, target: np.ndarray) -> SurfacePoint:
    closest, _, tri = trimesh.proximity.closest_point(mesh, target[None])
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)[0]
    bary = np.clip(bary, 0.0, 1.0)
    return SurfacePoint(part, int(tri[0]), bary / bary.sum())


def _box(center, extents) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def synthetic_face_model(subdivisions: int = 5) -> FaceModel:
    """An ellipsoid head with the anatomy the runtime needs (metres, MPEG-4 face frame)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    V = sphere.vertices * SEMI
    F = sphere.faces.astype(np.int32)
    skin = trimesh.Trimesh(V, F, process=False)

    inner_semi = SEMI - THICKNESS - 0.0015
    dense = trimesh.creation.icosphere(subdivisions=4).vertices * inner_semi
    chin = (dense[:, 1] < -0.035) & (dense[:, 2] > 0.0)
    cranium = trimesh.convex.convex_hull(dense[dense[:, 1] > -0.02])
    mandible = trimesh.convex.convex_hull(dense[chin])
    mouth_y = _on_ellipsoid(_dir(0.0, -0.28), SEMI)
    upper_teeth = _box(mouth_y + [0, 0.007, -0.022], [0.035, 0.012, 0.012])
    lower_teeth = _box(mouth_y + [0, -0.008, -0.024], [0.033, 0.012, 0.012])
    tongue = _box(mouth_y + [0, -0.006, -0.045], [0.03, 0.01, 0.04])
    eyes = {k: trimesh.creation.icosphere(subdivisions=2, radius=EYE_RADIUS).apply_translation(c)
            for k, c in EYE_CENTERS.items()}

    def part(mesh, bone, color):
        return Part(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32),
                    np.array(color, dtype=np.float32), bone)

    parts = {
        "cranium": part(cranium, "head", [0.9, 0.9, 0.85, 1]),
        "upper_teeth": part(upper_teeth, "head", [1, 1, 1, 1]),
        "mandible": part(mandible, "jaw", [0.9, 0.9, 0.85, 1]),
        "lower_teeth": part(lower_teeth, "jaw", [1, 1, 1, 1]),
        "tongue": part(tongue, "tongue", [0.8, 0.3, 0.3, 1]),
        "eye_l": part(eyes["eye_l"], "eye_l", [1, 1, 1, 1]),
        "eye_r": part(eyes["eye_r"], "eye_r", [1, 1, 1, 1]),
    }
    meshes = {"cranium": cranium, "mandible": mandible, "tongue": tongue, "eye_l": eyes["eye_l"], "eye_r": eyes["eye_r"]}

    fdp = {name: _surface_point(skin, "skin", _on_ellipsoid(_dir(*ae), SEMI)) for name, ae in FDP_DIRECTIONS.items()}
    for name, eye in (("3.5", "eye_l"), ("3.6", "eye_r")):
        fdp[name] = _surface_point(meshes[eye], eye, EYE_CENTERS[eye] + [0, 0, EYE_RADIUS])
    tip = mouth_y + [0, -0.006, -0.025]
    fdp["6.1"] = _surface_point(tongue, "tongue", tip)
    fdp["6.2"] = _surface_point(tongue, "tongue", mouth_y + [0, -0.001, -0.045])
    fdp["6.3"] = _surface_point(tongue, "tongue", mouth_y + [0.015, -0.001, -0.04])
    fdp["6.4"] = _surface_point(tongue, "tongue", mouth_y + [-0.015, -0.001, -0.04])
    fdp["7.1"] = _surface_point(cranium, "cranium", np.array([0.0, -0.09, -0.03]))

    # Regions by position.
    names = ["scalp", "forehead", "brow_l", "brow_r", "eyelid_l", "eyelid_r", "nose", "cheek_l", "cheek_r",
             "lip_upper", "lip_lower", "chin", "ear_l", "ear_r"]
    d = V / np.linalg.norm(V, axis=1, keepdims=True)
    el = np.arcsin(np.clip(d[:, 1], -1, 1))
    az = np.arctan2(d[:, 0], d[:, 2])
    region = np.zeros(len(V), dtype=np.int32)
    front = np.abs(az) < 1.1
    side = np.where(az > 0, 0, 1)
    region[front & (el > 0.3)] = names.index("forehead")
    region[front & (el > 0.2) & (el <= 0.3)] = np.array([names.index("brow_l"), names.index("brow_r")])[side[front & (el > 0.2) & (el <= 0.3)]]
    m = front & (el > 0.03) & (el <= 0.2) & (np.abs(az) > 0.15) & (np.abs(az) < 0.6)
    region[m] = np.array([names.index("eyelid_l"), names.index("eyelid_r")])[side[m]]
    m = front & (el > -0.2) & (el <= 0.2) & (np.abs(az) <= 0.15)
    region[m] = names.index("nose")
    m = front & (el > -0.45) & (el <= 0.2) & (region == 0)
    region[m] = np.array([names.index("cheek_l"), names.index("cheek_r")])[side[m]]
    lips = front & (np.abs(az) < 0.34) & (el > -0.36) & (el <= -0.2)
    region[lips & (el > -0.28)] = names.index("lip_upper")
    region[lips & (el <= -0.28)] = names.index("lip_lower")
    region[front & (el <= -0.36) & (np.abs(az) < 0.8)] = names.index("chin")
    m = (np.abs(az) >= 1.3) & (np.abs(az) < 1.9) & (np.abs(el) < 0.35)
    region[m] = np.array([names.index("ear_l"), names.index("ear_r")])[side[m]]

    def linear(name, att_part, att_target, ins_name, regions, zone=0.45):
        att = _surface_point(meshes[att_part], att_part, np.asarray(att_target, dtype=np.float64))
        a = meshes[att_part].triangles[att.triangle].T @ att.bary
        i = skin.triangles[fdp[ins_name].triangle].T @ fdp[ins_name].bary
        length = float(np.linalg.norm(i - a))
        return Muscle(name, "linear", att, fdp[ins_name], regions, zone_angle=zone,
                      fall_start=0.75 * length, fall_end=1.1 * length)

    muscles = []
    for s, side_name, sx in (("l", "l", 1.0), ("r", "r", -1.0)):
        o = "4.3" if s == "l" else "4.4"
        muscles += [
            linear(f"zygomatic_major_{s}", "cranium", [sx * 0.062, 0.005, 0.045], "8.3" if s == "l" else "8.4",
                   [f"cheek_{s}", "lip_upper", "lip_lower"]),
            linear(f"levator_labii_{s}", "cranium", [sx * 0.022, 0.015, 0.075], "8.5" if s == "l" else "8.6",
                   [f"cheek_{s}", "lip_upper", "nose"]),
            linear(f"depressor_anguli_{s}", "mandible", [sx * 0.04, -0.085, 0.045], "8.3" if s == "l" else "8.4",
                   [f"cheek_{s}", "lip_lower", "chin"]),
            linear(f"frontalis_{s}", "cranium", [sx * 0.03, 0.095, 0.03], o, ["forehead", f"brow_{s}"]),
            linear(f"corrugator_{s}", "cranium", [sx * 0.008, 0.035, 0.08], "4.1" if s == "l" else "4.2",
                   ["forehead", f"brow_{s}", "nose"], zone=0.6),
        ]
    muscles.append(linear("mentalis", "mandible", [0.0, -0.07, 0.06], "2.10", ["chin", "lip_lower"]))
    c = 0.5 * (skin.triangles[fdp["8.1"].triangle].T @ fdp["8.1"].bary + skin.triangles[fdp["8.2"].triangle].T @ fdp["8.2"].bary)
    muscles.append(Muscle("orbicularis_oris", "sphincter", _surface_point(skin, "skin", c), None,
                          ["lip_upper", "lip_lower"], semi_axes=np.array([0.03, 0.018]),
                          axes=np.array([[1.0, 0, 0], [0, 1.0, 0]])))

    mirror = trimesh.proximity.ProximityQuery(skin).vertex(V * [-1, 1, 1])[1].astype(np.int32)
    return FaceModel(
        skin_vertices=V, skin_faces=F, skin_uv=np.zeros((len(V), 2), np.float32),
        skin_color=np.array([0.8, 0.6, 0.5, 1], np.float32), skin_mirror=mirror, skin_region=region,
        region_names=names, skin_thickness=np.full(len(V), THICKNESS),
        layer_params={"layer_depth_fractions": [0.0, 0.5, 1.0]}, parts=parts,
        jaw_pivot=np.array([0.0, -0.005, -0.01]), jaw_axis=np.array([1.0, 0.0, 0.0]),
        eye_centers={k: v.copy() for k, v in EYE_CENTERS.items()}, feature_points=fdp, muscles=muscles,
        meta={"name": "synthetic ellipsoid head"},
    )


def test_synthetic_face_model_is_consistent():
    fm = synthetic_face_model(subdivisions=4)
    pos = fm.feature_point_positions()
    assert pos["8.3"][0] > 0 > pos["8.4"][0]            # the face's left is +x
    assert pos["2.2"][1] > pos["2.3"][1]                # upper inner lip above lower
    assert 0.007 < pos["3.1"][1] - pos["3.3"][1] < 0.013  # an iris-sized eye opening
    assert np.all(fm.skin_vertices[fm.skin_mirror][:, 0] * fm.skin_vertices[:, 0] <= 1e-9)
