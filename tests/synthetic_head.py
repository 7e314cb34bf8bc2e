"""The synthetic head of the tests: one small anatomical FaceModel built from ellipsoids.

A mirror-symmetric ellipsoidal skin (icosphere) with the FAP-bound feature points, regions
and Waters muscles (linear and a sphincter), a cranium and a mandible (convex hulls of an
inner ellipsoid), teeth and a tongue, and two eyeballs coloured white with a blue iris and
a black pupil. Metres, MPEG-4 face frame (x the face's
left, y up, z forward). Deterministic.
The render and video tests use a head of their own (tests/test_render_support.py): no
neck below the chin, eyes standing out of the skin, the lips cut apart, as their framing
and pixel checks need.

What differs between the tests that use it are the parameters:

    subdivisions  skin resolution (3: 642 vertices, 4: 2562, 5: 10242)
    all_points    every one of the 84 MPEG-4 feature points (a complete FaceModel file);
                  otherwise only those the runtime binds FAPs to
    complete      every field populated (implies all_points): two FaceDefTables and a
                  calibrated-looking fap_mapping of assorted dtypes, for the file format
    personalized  a scan transform other than the identity (mm, offset), as adapted heads have
"""

from __future__ import annotations

import numpy as np
import trimesh

from fae.io.facemodel import FaceDefTable, FaceModel, Muscle, Part, SurfacePoint
from fae.mpeg4 import FEATURE_POINTS

SEMI = np.array([0.078, 0.112, 0.098])  # skin ellipsoid semi-axes, metres
THICKNESS = 0.012
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
MOUTH_ELEVATION = -0.28  # between the inner lip points 2.2 and 2.3
REGION_NAMES = ["scalp", "forehead", "brow_l", "brow_r", "eyelid_l", "eyelid_r", "nose", "cheek_l", "cheek_r",
                "lip_upper", "lip_lower", "chin", "ear_l", "ear_r"]


def fdp_names_from_group_sizes() -> list[str]:
    """The 84 MPEG-4 feature point names, from the standard's group sizes."""
    sizes = {2: 14, 3: 14, 4: 6, 5: 4, 6: 4, 7: 1, 8: 10, 9: 15, 10: 10, 11: 6}
    return [f"{g}.{i}" for g, n in sizes.items() for i in range(1, n + 1)]


def _dir(az: float, el: float) -> np.ndarray:
    return np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])


def on_skin(az: float, el: float) -> np.ndarray:
    """The point of the skin ellipsoid in direction (azimuth, elevation) from its centre."""
    d = _dir(az, el)
    return d / np.sqrt(np.sum((d / SEMI) ** 2))


EYE_CENTERS = {"eye_l": np.array([0.032, 0.028, 0.066]), "eye_r": np.array([-0.032, 0.028, 0.066])}
MOUTH = on_skin(0.0, MOUTH_ELEVATION)  # the middle of the mouth on the closed skin


def _surface_point(mesh: trimesh.Trimesh, part: str, target) -> SurfacePoint:
    closest, _, tri = trimesh.proximity.closest_point(mesh, np.asarray(target, dtype=np.float64)[None])
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)[0]
    bary = np.clip(bary, 0.0, 1.0)
    return SurfacePoint(part, int(tri[0]), bary / bary.sum())


def _box(center, extents) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def _eye(centre: np.ndarray) -> tuple[trimesh.Trimesh, np.ndarray]:
    """An eyeball at `centre` and its vertex colours: white, a blue iris, a black pupil."""
    eye = trimesh.creation.icosphere(subdivisions=3, radius=EYE_RADIUS)
    cosang = eye.vertices[:, 2] / EYE_RADIUS
    colors = np.tile(np.array([0.85, 0.83, 0.80, 1.0], dtype=np.float32), (len(eye.vertices), 1))
    colors[cosang > np.cos(np.radians(38))] = (0.10, 0.22, 0.42, 1.0)
    colors[cosang > np.cos(np.radians(16))] = (0.01, 0.01, 0.01, 1.0)
    return eye.apply_translation(centre), colors


def _regions(V: np.ndarray) -> np.ndarray:
    names = REGION_NAMES
    d = V / np.linalg.norm(V, axis=1, keepdims=True)
    el = np.arcsin(np.clip(d[:, 1], -1, 1))
    az = np.arctan2(d[:, 0], d[:, 2])
    region = np.zeros(len(V), dtype=np.int32)
    front = np.abs(az) < 1.1
    side = np.where(az > 0, 0, 1)
    brow = front & (el > 0.2) & (el <= 0.3)
    region[front & (el > 0.3)] = names.index("forehead")
    region[brow] = np.array([names.index("brow_l"), names.index("brow_r")])[side[brow]]
    m = front & (el > 0.03) & (el <= 0.2) & (np.abs(az) > 0.15) & (np.abs(az) < 0.6)
    region[m] = np.array([names.index("eyelid_l"), names.index("eyelid_r")])[side[m]]
    m = front & (el > -0.2) & (el <= 0.2) & (np.abs(az) <= 0.15)
    region[m] = names.index("nose")
    m = front & (el > -0.45) & (el <= 0.2) & (region == 0)
    region[m] = np.array([names.index("cheek_l"), names.index("cheek_r")])[side[m]]
    lips = front & (np.abs(az) < 0.34) & (el > -0.36) & (el <= -0.2)
    region[lips & (el > MOUTH_ELEVATION)] = names.index("lip_upper")
    region[lips & (el <= MOUTH_ELEVATION)] = names.index("lip_lower")
    region[front & (el <= -0.36) & (np.abs(az) < 0.8)] = names.index("chin")
    m = (np.abs(az) >= 1.3) & (np.abs(az) < 1.9) & (np.abs(el) < 0.35)
    region[m] = np.array([names.index("ear_l"), names.index("ear_r")])[side[m]]
    return region


def synthetic_head(personalized: bool = True, *, subdivisions: int = 3, all_points: bool = False,
                   complete: bool = True) -> FaceModel:
    """The synthetic head (see the module docstring for the parameters); the default is the
    complete, personalized head of 642 skin vertices the file format tests write."""
    all_points = all_points or complete
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    V, F = np.asarray(sphere.vertices) * SEMI, np.asarray(sphere.faces, dtype=np.int32)
    skin = trimesh.Trimesh(V, F, process=False)

    inner_semi = SEMI - THICKNESS - 0.0015
    dense = trimesh.creation.icosphere(subdivisions=4).vertices * inner_semi
    chin = (dense[:, 1] < -0.035) & (dense[:, 2] > 0.0)
    cranium = trimesh.convex.convex_hull(dense[dense[:, 1] > -0.02])
    mandible = trimesh.convex.convex_hull(dense[chin])
    upper_teeth = _box(MOUTH + [0, 0.007, -0.022], [0.035, 0.012, 0.012])
    lower_teeth = _box(MOUTH + [0, -0.008, -0.024], [0.033, 0.012, 0.012])
    tongue = _box(MOUTH + [0, -0.006, -0.045], [0.03, 0.01, 0.04])
    eyes = {k: _eye(c) for k, c in EYE_CENTERS.items()}

    def part(mesh, bone, color, vertex_colors=None):
        return Part(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32),
                    np.array(color, dtype=np.float32), bone, vertex_colors)

    parts = {
        "cranium": part(cranium, "head", [0.9, 0.9, 0.85, 1]),
        "mandible": part(mandible, "jaw", [0.9, 0.9, 0.85, 1]),
        "upper_teeth": part(upper_teeth, "head", [1, 1, 1, 1]),
        "lower_teeth": part(lower_teeth, "jaw", [1, 1, 1, 1]),
        "tongue": part(tongue, "tongue", [0.8, 0.3, 0.3, 1]),
        "eye_l": part(eyes["eye_l"][0], "eye_l", [0.85, 0.83, 0.8, 1], eyes["eye_l"][1]),
        "eye_r": part(eyes["eye_r"][0], "eye_r", [0.85, 0.83, 0.8, 1], eyes["eye_r"][1]),
    }
    meshes = {"cranium": cranium, "mandible": mandible, "tongue": tongue,
              "eye_l": eyes["eye_l"][0], "eye_r": eyes["eye_r"][0]}

    fdp = {name: _surface_point(skin, "skin", on_skin(*ae)) for name, ae in FDP_DIRECTIONS.items()}
    for name, eye in (("3.5", "eye_l"), ("3.6", "eye_r")):
        fdp[name] = _surface_point(meshes[eye], eye, EYE_CENTERS[eye] + [0, 0, EYE_RADIUS])
    fdp["6.1"] = _surface_point(tongue, "tongue", MOUTH + [0, -0.006, -0.025])
    fdp["6.2"] = _surface_point(tongue, "tongue", MOUTH + [0, -0.001, -0.045])
    fdp["6.3"] = _surface_point(tongue, "tongue", MOUTH + [0.015, -0.001, -0.04])
    fdp["6.4"] = _surface_point(tongue, "tongue", MOUTH + [-0.015, -0.001, -0.04])
    fdp["7.1"] = _surface_point(cranium, "cranium", np.array([0.0, -0.09, -0.03]))
    if all_points:
        # the points no FAP moves here: the top (11.4) and back (11.6) of the skull where the
        # renderer's framing looks for them, the others on the skin spread over the upper head
        fdp["11.4"] = _surface_point(skin, "skin", on_skin(0.0, 0.5 * np.pi - 1e-3))
        fdp["11.6"] = _surface_point(skin, "skin", on_skin(np.pi, 0.0))
        for point in FEATURE_POINTS:
            if point.name not in fdp:
                az = point.side * (0.2 + 0.15 * ((point.index - 1) % 4))
                fdp[point.name] = _surface_point(skin, "skin", on_skin(az, 0.7 - 0.08 * (point.group - 2)))

    def position(p: SurfacePoint) -> np.ndarray:
        return (parts[p.part].vertices if p.part in parts else V)[(parts[p.part].faces if p.part in parts else F)[p.triangle]].T @ p.bary

    def linear(name, att_part, att_target, ins_name, regions, zone=0.45):
        att = _surface_point(meshes[att_part], att_part, att_target)
        length = float(np.linalg.norm(position(fdp[ins_name]) - position(att)))
        insertion = SurfacePoint("skin", fdp[ins_name].triangle, fdp[ins_name].bary.copy())  # its own, as read from a file
        return Muscle(name, "linear", att, insertion, regions, zone_angle=zone,
                      fall_start=0.75 * length, fall_end=1.1 * length)

    # the zygomatic majors and the orbicularis oris first (the file tests seed defects in them)
    zygomatic = [linear(f"zygomatic_major_{s}", "cranium", [sx * 0.062, 0.005, 0.045], ins,
                        [f"cheek_{s}", "lip_upper", "lip_lower"]) for s, sx, ins in (("l", 1.0, "8.3"), ("r", -1.0, "8.4"))]
    centre = 0.5 * (position(fdp["8.1"]) + position(fdp["8.2"]))
    muscles = [*zygomatic, Muscle("orbicularis_oris", "sphincter", _surface_point(skin, "skin", centre), None,
                                  ["lip_upper", "lip_lower"], semi_axes=np.array([0.03, 0.018]),
                                  axes=np.array([[1.0, 0, 0], [0, 1.0, 0]]))]
    for s, sx in (("l", 1.0), ("r", -1.0)):
        left = s == "l"
        muscles += [
            linear(f"levator_labii_{s}", "cranium", [sx * 0.022, 0.015, 0.075], "8.5" if left else "8.6",
                   [f"cheek_{s}", "lip_upper", "nose"]),
            linear(f"depressor_anguli_{s}", "mandible", [sx * 0.04, -0.085, 0.045], "8.3" if left else "8.4",
                   [f"cheek_{s}", "lip_lower", "chin"]),
            linear(f"frontalis_{s}", "cranium", [sx * 0.03, 0.095, 0.03], "4.3" if left else "4.4",
                   ["forehead", f"brow_{s}"]),
            linear(f"corrugator_{s}", "cranium", [sx * 0.008, 0.035, 0.08], "4.1" if left else "4.2",
                   ["forehead", f"brow_{s}", "nose"], zone=0.6),
        ]
    muscles.append(linear("mentalis", "mandible", [0.0, -0.07, 0.06], "2.10", ["chin", "lip_lower"]))

    mirror = trimesh.proximity.ProximityQuery(skin).vertex(V * [-1, 1, 1])[1].astype(np.int32)
    x, y, z = V.T
    uv = np.stack([0.5 + np.arctan2(x, z) / (2 * np.pi), 0.5 + np.arcsin(np.clip(y / SEMI[1], -1, 1)) / np.pi], axis=1)

    tables, fap_mapping = [], {}
    if complete:
        chin_v = np.argsort(np.linalg.norm(V - on_skin(0.0, -0.62), axis=1))[:5].astype(np.int32)
        brow_v = np.argsort(np.linalg.norm(V - on_skin(0.33, 0.26), axis=1))[:4].astype(np.int32)
        tables = [
            FaceDefTable(3, "skin", chin_v, np.array([0.0, 2048.0]), np.tile([0.0, -1.0e-5, 0.0], (1, 5, 1))),
            FaceDefTable(31, "skin", brow_v, np.array([-1024.0, 0.0, 512.0, 2048.0]),
                         np.linspace(0.0, 2e-5, 3 * 4 * 3).reshape(3, 4, 3)),
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
        skin_vertices=V, skin_faces=F, skin_uv=np.clip(uv, 0.0, 1.0).astype(np.float32),
        skin_color=np.array([0.80, 0.57, 0.46, 1.0], np.float32), skin_mirror=mirror, skin_region=_regions(V),
        region_names=list(REGION_NAMES), skin_thickness=np.full(len(V), THICKNESS),
        layer_params={"layer_depth_fractions": [0.0, 0.5, 1.0], "note": None}, parts=parts,
        jaw_pivot=np.array([0.0, -0.005, -0.01]), jaw_axis=np.array([1.0, 0.0, 0.0]),
        eye_centers={k: v.copy() for k, v in EYE_CENTERS.items()}, feature_points=fdp, muscles=muscles,
        face_def_tables=tables, fap_mapping=fap_mapping, scan_transform=scan,
        meta={"name": "synthetic head", "generator": "tests/synthetic_head.py", "tags": ["test", "synthetic"]},
    )
