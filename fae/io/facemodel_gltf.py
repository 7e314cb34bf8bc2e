"""FaceModel <-> binary glTF 2.0 (.glb): the one file format of every fae head.

A FaceModel file is an ordinary .glb that any viewer opens: one named node and mesh per
surface ("skin", "cranium", "mandible", ...) with float32 POSITION/NORMAL, TEXCOORD_0 on
the skin, COLOR_0 where a part has vertex colours, and a PBR material per mesh. Everything
the engine needs, bit-exact, lives in the extension ``FAE_face_model`` on the glTF root
(declared in ``extensionsUsed`` only, so viewers that do not know it still open the file);
its large arrays sit in buffer views of the same binary chunk, described by small JSON
records ``{"dtype", "shape", "bufferView"}``. docs/facemodel.md specifies the layout.

    write_facemodel(model, path)        atomic, deterministic
    read_facemodel(path) -> FaceModel   exact inverse of write_facemodel
    structural_problems(model) -> list[str]
    facemodel_to_glb(model) -> bytes, facemodel_from_glb(data, name) -> FaceModel
"""

from __future__ import annotations

import json
import math
import os
import struct
from pathlib import Path

import numpy as np
import pygltflib

from fae.io.atomic import atomic_path
from fae.io.facemodel import BONES, FACE_DEF_TABLE_SOURCES, PART_BONES, FaceDefTable, FaceModel, Muscle, Part, SurfacePoint
from fae.mesh import seamed_surface, vertex_normals, wrapped_seam
from fae.mpeg4 import FEATURE_POINTS, fapu0_from_positions, fapu_from_fapu0

EXTENSION = "FAE_face_model"
FORMAT_VERSION = 1
GENERATOR = f"fae FaceModel writer ({EXTENSION} {FORMAT_VERSION})"

MUSCLE_KINDS = ("linear", "sphincter")
EYES = ("eye_l", "eye_r")

# Perceptual roughness of each surface's PBR material (metallic is 0 everywhere).
ROUGHNESS = {
    "skin": 0.6,
    "cranium": 0.8,
    "mandible": 0.8,
    "upper_teeth": 0.3,
    "lower_teeth": 0.3,
    "tongue": 0.45,
    "eye_l": 0.15,
    "eye_r": 0.15,
}
DEFAULT_ROUGHNESS = 0.6

_TOLERANCE = 1e-6
_ALIGNMENT = 8
_GLB_MAGIC = b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963


class FaceModelError(ValueError):
    """A FaceModel file (or model) is unreadable or inconsistent; the message names the
    file and the field, and says what was expected."""


# --------------------------------------------------------------------------------------
# structural checks


def structural_problems(model: FaceModel, fdp_names: list[str] | None = None) -> list[str]:
    """Everything wrong with `model`'s structure, one message per problem ([] if none).

    Checks shapes, dtypes and finiteness of every array, index ranges (faces, mirror,
    regions, triangles of surface points, FaceDefTable vertices), barycentric coordinates
    (>= 0, summing to 1), a unit-length jaw axis, known part bones and muscle kinds,
    FaceDefTable consistency (borders increasing and containing 0, displacements of shape
    (m, k, 3)), plain-JSON `layer_params`/`meta`, and that every name in `fdp_names`
    (default: the 84 MPEG-4 feature points from fae.mpeg4) has a feature point.
    Each message starts with the field it is about.
    """
    problems: list[str] = []
    add = problems.append
    mesh_sizes: dict[str, tuple[int, int]] = {}

    n_verts = _check_array(add, "skin_vertices", model.skin_vertices, np.float64, (None, 3))
    _check_metres(add, "skin_vertices", model.skin_vertices)
    _check_metres(add, "jaw_pivot", model.jaw_pivot)
    if isinstance(model.eye_centers, dict):
        for key, centre in model.eye_centers.items():
            _check_metres(add, f"eye_centers[{key!r}]", centre)
    n_faces = _check_array(add, "skin_faces", model.skin_faces, np.int32, (None, 3))
    if n_verts is not None and n_faces is not None:
        _check_index_range(add, "skin_faces", model.skin_faces, n_verts, "skin vertex")
        mesh_sizes["skin"] = (n_verts, n_faces)
        if n_faces == 0:
            add("skin_faces: expected at least one triangle")
    if _check_array(add, "skin_uv", model.skin_uv, np.float32, (n_verts, 2)) is not None:
        _check_unit_interval(add, "skin_uv", model.skin_uv)
    _check_color(add, "skin_color", model.skin_color)
    texture = getattr(model, "skin_texture", None)
    if texture is not None:
        _check_array(add, "skin_texture", texture, np.uint8, (None, None, 3))
        if isinstance(texture, np.ndarray) and texture.ndim == 3 and min(texture.shape[:2]) < 1:
            add(f"skin_texture: expected an image of at least 1x1 pixels, got shape {texture.shape}")
    if _check_array(add, "skin_mirror", model.skin_mirror, np.int32, (n_verts,)) is not None and n_verts:
        if _check_index_range(add, "skin_mirror", model.skin_mirror, n_verts, "skin vertex"):
            m = model.skin_mirror
            bad = np.flatnonzero(m[m] != np.arange(n_verts))
            if bad.size:
                add(f"skin_mirror: expected a symmetric pairing (mirror[mirror[i]] == i); fails at vertex {int(bad[0])}")
    names = model.region_names
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        add("region_names: expected a list of non-empty strings")
        names = []
    elif len(set(names)) != len(names):
        add("region_names: expected unique names")
    if _check_array(add, "skin_region", model.skin_region, np.int32, (n_verts,)) is not None:
        _check_index_range(add, "skin_region", model.skin_region, len(names), "region_names entry")
    if _check_array(add, "skin_thickness", model.skin_thickness, np.float64, (n_verts,)) is not None:
        if np.any(model.skin_thickness < 0):
            add("skin_thickness: expected depths >= 0 metres")
    _check_plain_json(add, "layer_params", model.layer_params, require_dict=True)

    if not isinstance(model.parts, dict):
        add("parts: expected a dict of part name -> Part")
    else:
        for name, part in model.parts.items():
            field = f"parts[{name!r}]"
            if not isinstance(name, str) or not name or name == "skin":
                add(f"{field}: expected a non-empty part name other than 'skin'")
                continue
            if not isinstance(part, Part):
                add(f"{field}: expected a Part, got {type(part).__name__}")
                continue
            pv = _check_array(add, f"{field}.vertices", part.vertices, np.float64, (None, 3))
            _check_metres(add, f"{field}.vertices", part.vertices)
            pf = _check_array(add, f"{field}.faces", part.faces, np.int32, (None, 3))
            if pv is not None and pf is not None:
                _check_index_range(add, f"{field}.faces", part.faces, pv, "vertex")
                mesh_sizes[name] = (pv, pf)
                if pf == 0:
                    add(f"{field}.faces: expected at least one triangle")
            _check_color(add, f"{field}.color", part.color)
            if part.vertex_colors is not None:
                if _check_array(add, f"{field}.vertex_colors", part.vertex_colors, np.float32, (pv, 4)) is not None:
                    _check_unit_interval(add, f"{field}.vertex_colors", part.vertex_colors)
            expected_bone = PART_BONES.get(name)
            if part.bone not in BONES:
                add(f"{field}.bone: expected one of {', '.join(BONES)}, got {part.bone!r}")
            elif expected_bone is not None and part.bone != expected_bone:
                add(f"{field}.bone: expected {expected_bone!r} for this part, got {part.bone!r}")

    _check_array(add, "jaw_pivot", model.jaw_pivot, np.float64, (3,))
    if _check_array(add, "jaw_axis", model.jaw_axis, np.float64, (3,)) is not None:
        norm = float(np.linalg.norm(model.jaw_axis))
        if abs(norm - 1.0) > _TOLERANCE:
            add(f"jaw_axis: expected a unit vector, length is {norm:.9g}")
    if not isinstance(model.eye_centers, dict):
        add("eye_centers: expected a dict {'eye_l': (3,), 'eye_r': (3,)}")
    else:
        for key, centre in model.eye_centers.items():
            if key not in EYES:
                add(f"eye_centers[{key!r}]: expected only the keys 'eye_l' and 'eye_r'")
            else:
                _check_array(add, f"eye_centers[{key!r}]", centre, np.float64, (3,))
        if isinstance(model.parts, dict):
            for eye in EYES:
                if eye in model.parts and eye not in model.eye_centers:
                    add(f"eye_centers: expected a centre for part {eye!r}")

    if not isinstance(model.feature_points, dict):
        add("feature_points: expected a dict of FDP name -> SurfacePoint")
    else:
        for name, point in model.feature_points.items():
            _check_surface_point(add, f"feature_points[{name!r}]", point, mesh_sizes)
        if fdp_names is None:
            fdp_names = [p.name for p in FEATURE_POINTS]
        missing = [n for n in fdp_names if n not in model.feature_points]
        if missing:
            add(f"feature_points: expected all {len(fdp_names)} MPEG-4 feature points; missing {', '.join(missing)}")

    if not isinstance(model.muscles, list):
        add("muscles: expected a list of Muscle")
    else:
        seen: set[str] = set()
        for i, muscle in enumerate(model.muscles):
            field = f"muscles[{i}]"
            if not isinstance(muscle, Muscle):
                add(f"{field}: expected a Muscle, got {type(muscle).__name__}")
                continue
            if not isinstance(muscle.name, str) or not muscle.name:
                add(f"{field}.name: expected a non-empty string")
            elif muscle.name in seen:
                add(f"{field}.name: expected unique muscle names, {muscle.name!r} repeats")
            else:
                seen.add(muscle.name)
            field = f"muscles[{i}] ({muscle.name})"
            _check_muscle(add, field, muscle, mesh_sizes, set(names))

    if not isinstance(model.face_def_tables, list):
        add("face_def_tables: expected a list of FaceDefTable")
    else:
        for i, table in enumerate(model.face_def_tables):
            _check_face_def_table(add, f"face_def_tables[{i}]", table, mesh_sizes)

    if not isinstance(model.fap_mapping, dict):
        add("fap_mapping: expected a dict of name -> ndarray")
    else:
        for key, value in model.fap_mapping.items():
            if not isinstance(key, str) or not key:
                add(f"fap_mapping[{key!r}]: expected a non-empty string key")
            elif not isinstance(value, np.ndarray):
                add(f"fap_mapping[{key!r}]: expected an ndarray, got {type(value).__name__}")
            elif value.dtype.kind in "OV":
                add(f"fap_mapping[{key!r}]: expected a numeric or fixed-width string dtype, got {value.dtype}")

    if _check_array(add, "scan_transform", model.scan_transform, np.float64, (4, 4)) is not None:
        if not np.array_equal(model.scan_transform[3], [0.0, 0.0, 0.0, 1.0]):
            add("scan_transform: expected an affine matrix (last row 0, 0, 0, 1)")
    _check_plain_json(add, "meta", model.meta, require_dict=True)
    return problems


def _check_array(add, field: str, value, dtype, shape: tuple) -> int | None:
    """Check an ndarray's dtype, shape (None: any length) and finiteness.

    Returns its first dimension when usable (so callers can range-check), else None.
    """
    if not isinstance(value, np.ndarray):
        add(f"{field}: expected a {np.dtype(dtype).name} ndarray of shape {_shape_text(shape)}, got {type(value).__name__}")
        return None
    if value.dtype != np.dtype(dtype):
        add(f"{field}: expected dtype {np.dtype(dtype).name}, got {value.dtype}")
    if value.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, value.shape)):
        add(f"{field}: expected shape {_shape_text(shape)}, got {tuple(value.shape)}")
        return None
    if value.dtype.kind not in "iuf":
        return None
    if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
        add(f"{field}: expected finite values, found NaN or infinity")
    return int(value.shape[0])


MAX_COORDINATE = 1000.0  # metres: a head's coordinates lie within a metre or so of its origin


def _check_metres(add, field: str, value) -> None:
    """Coordinates beyond MAX_COORDINATE metres (1e160: finite, yet the renderer's matrices
    turned singular) are not a head's."""
    if isinstance(value, np.ndarray) and value.dtype.kind == "f" and value.size:
        largest = float(np.nanmax(np.abs(np.where(np.isfinite(value), value, 0.0))))
        if largest > MAX_COORDINATE:
            add(f"{field}: expected metres (a head within {MAX_COORDINATE:g} m of its origin), "
                f"found a coordinate of {largest:.3g}")


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join("n" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _check_index_range(add, field: str, index: np.ndarray, count: int, what: str) -> bool:
    if index.dtype.kind not in "iu":
        return False
    if index.size and (index.min() < 0 or index.max() >= count):
        bad = int(index[(index < 0) | (index >= count)].flat[0])
        add(f"{field}: expected {what} indices in [0, {count}), found {bad}")
        return False
    return True


def _check_unit_interval(add, field: str, values: np.ndarray) -> None:
    if values.size and (values.min() < 0.0 or values.max() > 1.0):
        add(f"{field}: expected values in [0, 1]")


def _check_color(add, field: str, color) -> None:
    if _check_array(add, field, color, np.float32, (4,)) is not None:
        _check_unit_interval(add, field, color)


def _check_surface_point(add, field: str, point, mesh_sizes: dict[str, tuple[int, int]]) -> None:
    if not isinstance(point, SurfacePoint):
        add(f"{field}: expected a SurfacePoint, got {type(point).__name__}")
        return
    if point.part not in mesh_sizes:
        add(f"{field}.part: expected 'skin' or a part of this model, got {point.part!r}")
    elif not isinstance(point.triangle, (int, np.integer)) or isinstance(point.triangle, bool):
        add(f"{field}.triangle: expected an int, got {type(point.triangle).__name__}")
    elif not 0 <= point.triangle < mesh_sizes[point.part][1]:
        add(f"{field}.triangle: expected a triangle of {point.part!r} in [0, {mesh_sizes[point.part][1]}), got {point.triangle}")
    if _check_array(add, f"{field}.bary", point.bary, np.float64, (3,)) is not None:
        if point.bary.min() < -_TOLERANCE or abs(float(point.bary.sum()) - 1.0) > _TOLERANCE:
            add(f"{field}.bary: expected barycentric coordinates >= 0 summing to 1, got {point.bary.tolist()}")


def _check_muscle(add, field: str, muscle: Muscle, mesh_sizes, region_names: set[str]) -> None:
    if muscle.kind not in MUSCLE_KINDS:
        add(f"{field}.kind: expected one of {', '.join(MUSCLE_KINDS)}, got {muscle.kind!r}")
    _check_surface_point(add, f"{field}.attachment", muscle.attachment, mesh_sizes)
    if muscle.insertion is not None:
        _check_surface_point(add, f"{field}.insertion", muscle.insertion, mesh_sizes)
    if not isinstance(muscle.regions, list) or not all(isinstance(r, str) for r in muscle.regions):
        add(f"{field}.regions: expected a list of region names")
    else:
        unknown = [r for r in muscle.regions if r not in region_names]
        if unknown:
            add(f"{field}.regions: expected names from region_names, got {', '.join(map(repr, unknown))}")
    for attr in ("zone_angle", "fall_start", "fall_end"):
        value = getattr(muscle, attr)
        if not isinstance(value, (int, float, np.floating, np.integer)) or isinstance(value, bool) or not math.isfinite(value) or value < 0:
            add(f"{field}.{attr}: expected a finite number >= 0, got {value!r}")
    if muscle.kind == "linear":
        if muscle.insertion is None:
            add(f"{field}.insertion: expected a SurfacePoint for a linear muscle")
        if isinstance(muscle.fall_start, (int, float)) and isinstance(muscle.fall_end, (int, float)) and muscle.fall_end < muscle.fall_start:
            add(f"{field}.fall_end: expected >= fall_start ({muscle.fall_start}), got {muscle.fall_end}")
        if isinstance(muscle.zone_angle, (int, float)) and not 0 < muscle.zone_angle < math.pi:
            add(f"{field}.zone_angle: expected a half-angle in (0, pi) radians, got {muscle.zone_angle}")
    elif muscle.kind == "sphincter":
        if muscle.semi_axes is None:
            add(f"{field}.semi_axes: expected (2,) float64 metres for a sphincter muscle")
        elif _check_array(add, f"{field}.semi_axes", muscle.semi_axes, np.float64, (2,)) is not None and np.any(muscle.semi_axes <= 0):
            add(f"{field}.semi_axes: expected positive lengths, got {muscle.semi_axes.tolist()}")
        if muscle.axes is None:
            add(f"{field}.axes: expected (2, 3) float64 unit vectors for a sphincter muscle")
        elif _check_array(add, f"{field}.axes", muscle.axes, np.float64, (2, 3)) is not None:
            if np.any(np.abs(np.linalg.norm(muscle.axes, axis=1) - 1.0) > _TOLERANCE):
                add(f"{field}.axes: expected unit vectors")
    for attr in ("semi_axes", "axes"):
        value = getattr(muscle, attr)
        if muscle.kind == "linear" and value is not None:
            _check_array(add, f"{field}.{attr}", value, np.float64, (2,) if attr == "semi_axes" else (2, 3))


def _check_face_def_table(add, field: str, table, mesh_sizes) -> None:
    if not isinstance(table, FaceDefTable):
        add(f"{field}: expected a FaceDefTable, got {type(table).__name__}")
        return
    if not isinstance(table.fap, (int, np.integer)) or isinstance(table.fap, bool) or not 3 <= table.fap <= 68:
        add(f"{field}.fap: expected a low-level FAP number in 3..68, got {table.fap!r}")
    if table.part not in mesh_sizes:
        add(f"{field}.part: expected 'skin' or a part of this model, got {table.part!r}")
    k = _check_array(add, f"{field}.vertices", table.vertices, np.int32, (None,))
    if k is not None and table.part in mesh_sizes:
        _check_index_range(add, f"{field}.vertices", table.vertices, mesh_sizes[table.part][0], f"{table.part} vertex")
    b = _check_array(add, f"{field}.borders", table.borders, np.float64, (None,))
    m = None
    if b is not None:
        if b < 2:
            add(f"{field}.borders: expected at least 2 borders, got {b}")
        elif np.any(np.diff(table.borders) <= 0):
            add(f"{field}.borders: expected strictly increasing values, got {table.borders.tolist()}")
        elif not table.borders[0] <= 0.0 <= table.borders[-1]:
            add(f"{field}.borders: expected the intervals to contain 0, got {table.borders.tolist()}")
        else:
            m = b - 1
    _check_array(add, f"{field}.displacements", table.displacements, np.float64, (m, k, 3))
    if table.source not in FACE_DEF_TABLE_SOURCES:
        add(f"{field}.source: expected one of {', '.join(FACE_DEF_TABLE_SOURCES)}, got {table.source!r}")


def _check_plain_json(add, field: str, value, require_dict: bool = False) -> None:
    if require_dict and not isinstance(value, dict):
        add(f"{field}: expected a dict, got {type(value).__name__}")
        return
    if type(value) is dict:
        for key, item in value.items():
            if type(key) is not str:
                add(f"{field}: expected string keys, got {key!r}")
            else:
                _check_plain_json(add, f"{field}[{key!r}]", item)
    elif type(value) is list:
        for i, item in enumerate(value):
            _check_plain_json(add, f"{field}[{i}]", item)
    elif type(value) is float:
        if not math.isfinite(value):
            add(f"{field}: expected a finite number, got {value}")
    elif value is not None and type(value) not in (str, int, bool):
        add(f"{field}: expected plain JSON (dict, list, str, int, float, bool, None), got {type(value).__name__}")


# --------------------------------------------------------------------------------------
# writing


def write_facemodel(model: FaceModel, path: str | os.PathLike, *, check: bool = True) -> None:
    """Write `model` to `path` as a FaceModel .glb (atomic: the file appears complete or not at all).

    With `check` (default) a model with structural problems is refused with a
    FaceModelError listing them; `check=False` writes whatever can be encoded.
    """
    data = facemodel_to_glb(model, check=check, name=str(path))
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def facemodel_to_glb(model: FaceModel, *, check: bool = True, name: str = "<FaceModel>") -> bytes:
    """The .glb bytes of `model` (deterministic: the same model gives the same bytes)."""
    if check:
        problems = structural_problems(model)
        if problems:
            raise FaceModelError(f"{name}: refusing to write an inconsistent FaceModel: " + "; ".join(problems))
    try:
        return _Writer(model, name).glb()
    except FaceModelError:
        raise
    except (TypeError, ValueError, OverflowError) as exc:  # e.g. NaN bounds with check=False
        raise FaceModelError(f"{name}: cannot encode the FaceModel ({type(exc).__name__}: {exc})") from exc


class _Writer:
    def __init__(self, model: FaceModel, name: str):
        self.model = model
        self.name = name
        self.gltf = pygltflib.GLTF2()
        self.blob = bytearray()
        self.views_by_bytes: dict[bytes, int] = {}

    # binary chunk -------------------------------------------------------------------
    def _view(self, data: bytes, target: int | None) -> int:
        self.blob += b"\0" * (-len(self.blob) % _ALIGNMENT)
        index = len(self.gltf.bufferViews)
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data), target=target))
        self.blob += data
        self.views_by_bytes.setdefault(data, index)
        return index

    def array(self, field: str, value) -> dict:
        """The JSON record of an ndarray; its bytes go to a (possibly shared) buffer view."""
        if not isinstance(value, np.ndarray) or value.dtype.kind in "OV":
            raise FaceModelError(f"{self.name}: {field}: expected a numeric ndarray, got {getattr(value, 'dtype', type(value).__name__)}")
        data = np.ascontiguousarray(value).tobytes()
        record = {"dtype": value.dtype.str, "shape": [int(s) for s in value.shape]}
        if data:
            view = self.views_by_bytes.get(data)
            record["bufferView"] = view if view is not None else self._view(data, None)
        return record

    def accessor(self, values: np.ndarray, component: int, kind: str, target: int, bounds: bool = False) -> int:
        view = self._view(np.ascontiguousarray(values).tobytes(), target)
        acc = pygltflib.Accessor(bufferView=view, componentType=component, count=int(values.shape[0]), type=kind)
        if bounds:
            acc.min = [float(v) for v in values.min(axis=0)]
            acc.max = [float(v) for v in values.max(axis=0)]
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    # meshes ------------------------------------------------------------------------
    def image(self, rgb: np.ndarray) -> int:
        """Add an (H, W, 3) uint8 image as a PNG in the binary chunk; its glTF image index."""
        self.gltf.images.append(pygltflib.Image(bufferView=self._view(png_bytes(rgb), None), mimeType="image/png"))
        return len(self.gltf.images) - 1

    def mesh_node(self, name: str, vertices, faces, color, uv=None, vertex_colors=None,
                  texture: int | None = None, normals: np.ndarray | None = None) -> int | None:
        """Add the render mesh, material and node of one surface; None if it has no triangles.
        texture: a glTF image index that becomes the material's base colour texture (with uv);
        normals (n, 3): instead of the mesh's own."""
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces)
        if len(vertices) == 0 or len(faces) == 0:
            return None
        positions = vertices.astype(np.float32)
        normals = vertex_normals(vertices, faces) if normals is None else normals
        attributes = pygltflib.Attributes(
            POSITION=self.accessor(positions, pygltflib.FLOAT, pygltflib.VEC3, _ARRAY_BUFFER, bounds=True),
            NORMAL=self.accessor(np.asarray(normals, dtype=np.float32), pygltflib.FLOAT, pygltflib.VEC3, _ARRAY_BUFFER),
        )
        if uv is not None:
            attributes.TEXCOORD_0 = self.accessor(np.asarray(uv, dtype=np.float32), pygltflib.FLOAT, pygltflib.VEC2, _ARRAY_BUFFER)
        if vertex_colors is not None:
            attributes.COLOR_0 = self.accessor(np.asarray(vertex_colors, dtype=np.float32), pygltflib.FLOAT, pygltflib.VEC4, _ARRAY_BUFFER)
        indices = self.accessor(faces.astype(np.uint32).reshape(-1), pygltflib.UNSIGNED_INT, pygltflib.SCALAR, _ELEMENT_ARRAY_BUFFER)

        base = [1.0, 1.0, 1.0, 1.0] if vertex_colors is not None else [float(c) for c in np.asarray(color, dtype=np.float32)]
        base = [min(max(c, 0.0), 1.0) for c in base]
        base_texture = None
        if texture is not None and uv is not None:
            base_texture = wrapped_texture(self.gltf, texture)
            base = [1.0, 1.0, 1.0, 1.0]
        material = pygltflib.Material(
            name=name,
            pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorFactor=base, metallicFactor=0.0, roughnessFactor=ROUGHNESS.get(name, DEFAULT_ROUGHNESS),
                baseColorTexture=base_texture,
            ),
            alphaMode=pygltflib.BLEND if base[3] < 1.0 else None,
            doubleSided=False,
        )
        self.gltf.materials.append(material)
        primitive = pygltflib.Primitive(attributes=attributes, indices=indices, material=len(self.gltf.materials) - 1, mode=pygltflib.TRIANGLES)
        self.gltf.meshes.append(pygltflib.Mesh(name=name, primitives=[primitive]))
        self.gltf.nodes.append(pygltflib.Node(name=name, mesh=len(self.gltf.meshes) - 1))
        return len(self.gltf.nodes) - 1

    # the whole file ----------------------------------------------------------------
    def glb(self) -> bytes:
        m = self.model
        texture = None if m.skin_texture is None else self.image(np.asarray(m.skin_texture))
        if texture is None:
            skin_node = self.mesh_node("skin", m.skin_vertices, m.skin_faces, m.skin_color, uv=m.skin_uv)
        else:  # viewers get the seam's triangles on their own vertex copies (fae.mesh.wrapped_seam)
            V2, F2, uv2, N2, _ = seamed_surface(m.skin_vertices, m.skin_faces, m.skin_uv)
            skin_node = self.mesh_node("skin", V2, F2, m.skin_color, uv=uv2, texture=texture, normals=N2)
        part_nodes = {
            name: self.mesh_node(name, part.vertices, part.faces, part.color, vertex_colors=part.vertex_colors)
            for name, part in m.parts.items()
        }
        ext = {
            "version": FORMAT_VERSION,
            "skin": {
                "node": skin_node,
                "vertices": self.array("skin_vertices", m.skin_vertices),
                "faces": self.array("skin_faces", m.skin_faces),
                "uv": self.array("skin_uv", m.skin_uv),
                "color": _float_list(m.skin_color, np.float32),
                "mirror": self.array("skin_mirror", m.skin_mirror),
                "region": self.array("skin_region", m.skin_region),
                "thickness": self.array("skin_thickness", m.skin_thickness),
                **({} if texture is None else {"texture": {"image": texture}}),  # untextured files stay byte-identical
            },
            "region_names": list(m.region_names),
            "layer_params": m.layer_params,
            "parts": {
                name: {
                    "node": part_nodes[name],
                    "bone": part.bone,
                    "vertices": self.array(f"parts[{name!r}].vertices", part.vertices),
                    "faces": self.array(f"parts[{name!r}].faces", part.faces),
                    "color": _float_list(part.color, np.float32),
                    "vertex_colors": None if part.vertex_colors is None else self.array(f"parts[{name!r}].vertex_colors", part.vertex_colors),
                }
                for name, part in m.parts.items()
            },
            "jaw": {"pivot": _float_list(m.jaw_pivot), "axis": _float_list(m.jaw_axis)},
            "eye_centers": {key: _float_list(c) for key, c in m.eye_centers.items()},
            "feature_points": {name: _surface_point_json(p) for name, p in m.feature_points.items()},
            "muscles": [self.muscle(i, mu) for i, mu in enumerate(m.muscles)],
            "face_def_tables": [
                {
                    "fap": int(t.fap),
                    "part": t.part,
                    "vertices": self.array(f"face_def_tables[{i}].vertices", t.vertices),
                    "borders": self.array(f"face_def_tables[{i}].borders", t.borders),
                    "displacements": self.array(f"face_def_tables[{i}].displacements", t.displacements),
                    **({} if t.source == "authored" else {"source": t.source}),  # older files stay byte-identical
                }
                for i, t in enumerate(m.face_def_tables)
            ],
            "fap_mapping": {key: self.array(f"fap_mapping[{key!r}]", v) for key, v in m.fap_mapping.items()},
            "scan_transform": [_float_list(row) for row in np.asarray(m.scan_transform, dtype=np.float64)],
            "meta": m.meta,
            "fapu": _fapu_or_none(m),
        }
        try:
            json.dumps(ext, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise FaceModelError(f"{self.name}: {EXTENSION}: cannot encode as JSON ({exc}); layer_params and meta must be plain JSON") from exc

        g = self.gltf
        g.asset = pygltflib.Asset(version="2.0", generator=GENERATOR)
        nodes = [n for n in [skin_node, *part_nodes.values()] if n is not None]
        g.scenes = [pygltflib.Scene(name=str(m.meta.get("name", "face")) if isinstance(m.meta, dict) else "face", nodes=nodes)]
        g.scene = 0
        g.extensionsUsed = [EXTENSION]
        g.extensions = {EXTENSION: ext}
        self.blob += b"\0" * (-len(self.blob) % _ALIGNMENT)
        g.buffers = [pygltflib.Buffer(byteLength=len(self.blob))]
        g.set_binary_blob(bytes(self.blob))
        g.set_min_alignment(_ALIGNMENT)
        return b"".join(g.save_to_bytes())

    def muscle(self, i: int, mu: Muscle) -> dict:
        return {
            "name": mu.name,
            "kind": mu.kind,
            "attachment": _surface_point_json(mu.attachment),
            "insertion": None if mu.insertion is None else _surface_point_json(mu.insertion),
            "regions": list(mu.regions),
            "zone_angle": float(mu.zone_angle),
            "fall_start": float(mu.fall_start),
            "fall_end": float(mu.fall_end),
            "semi_axes": None if mu.semi_axes is None else _float_list(mu.semi_axes),
            "axes": None if mu.axes is None else [_float_list(a) for a in np.asarray(mu.axes)],
        }


def wrapped_texture(gltf: pygltflib.GLTF2, image: int) -> pygltflib.TextureInfo:
    """A texture of glTF image `image` in `gltf`, sampled wrapping around in u (the skin's
    cylindrical map; fae.mesh.wrapped_seam) and clamped in v; the sampler is added once."""
    if not gltf.samplers:
        gltf.samplers.append(pygltflib.Sampler(magFilter=pygltflib.LINEAR, minFilter=pygltflib.LINEAR_MIPMAP_LINEAR,
                                               wrapS=pygltflib.REPEAT, wrapT=pygltflib.CLAMP_TO_EDGE))
    gltf.textures.append(pygltflib.Texture(sampler=0, source=image))
    return pygltflib.TextureInfo(index=len(gltf.textures) - 1)


def texture_factors(skin_colors: np.ndarray, skin_color) -> np.ndarray:
    """(V, 3) float in [0, 1]: the colours a skin is drawn in (fae.render.renderer.skin_colors)
    as factors of its texture: 1 where they are the skin colour, darker inside the mouth."""
    base = np.maximum(np.asarray(skin_color, dtype=np.float64).ravel()[:3], 1e-3)
    return np.clip(np.asarray(skin_colors, dtype=np.float64)[:, :3] / base, 0.0, 1.0)


def png_bytes(rgb: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 image as PNG bytes (lossless: png_pixels gives it back exactly)."""
    import io

    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB").save(out, format="PNG", compress_level=6)
    return out.getvalue()


def png_pixels(data: bytes) -> np.ndarray:
    """(H, W, 3) uint8 pixels of PNG (or JPEG) bytes; ValueError when they are not an image."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(bytes(data))) as image:
            return np.asarray(image.convert("RGB"), dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise ValueError(f"expected a PNG or JPEG image ({exc})") from exc


def _float_list(values, dtype=np.float64) -> list[float]:
    return [float(v) for v in np.asarray(values, dtype=dtype).reshape(-1)]


def _surface_point_json(p: SurfacePoint) -> dict:
    return {"part": p.part, "triangle": int(p.triangle), "bary": _float_list(p.bary)}


def _fapu_or_none(model: FaceModel) -> dict | None:
    """The model's FAPU (fae.mpeg4), or None when its feature points do not define them."""
    try:
        return fapu_from_fapu0(fapu0_from_positions(model.feature_point_positions()))
    except (IndexError, KeyError, TypeError, ValueError):
        return None


# --------------------------------------------------------------------------------------
# reading


def read_facemodel(path: str | os.PathLike, *, check: bool = True) -> FaceModel:
    """The FaceModel stored in the .glb at `path`.

    Raises FaceModelError (naming the file and the field) when the file is not binary
    glTF, carries no FAE_face_model extension, is truncated, or is inconsistent; with
    `check` (default) also when the decoded model has structural problems.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FaceModelError(f"{path}: cannot read the file ({exc.strerror or exc})") from exc
    return facemodel_from_glb(data, name=str(path), check=check)


def facemodel_from_glb(data: bytes, *, name: str = "<bytes>", check: bool = True) -> FaceModel:
    """Decode FaceModel .glb bytes; `name` is used in error messages."""
    try:
        model = _Reader(data, name).model()
    except FaceModelError:
        raise
    except (AttributeError, IndexError, KeyError, TypeError, ValueError, OverflowError, MemoryError, struct.error) as exc:
        # a malformation the field checks above did not anticipate: still name the file
        raise FaceModelError(f"{name}: malformed FaceModel file ({type(exc).__name__}: {exc})") from exc
    if check:
        problems = structural_problems(model)
        if problems:
            raise FaceModelError(f"{name}: inconsistent FaceModel: " + "; ".join(problems))
    return model


class _Reader:
    def __init__(self, data: bytes, name: str):
        self.name = name
        json_chunk, self.blob = self._chunks(bytes(data))
        try:
            self.gltf = pygltflib.GLTF2.from_json(json_chunk.decode("utf-8"), infer_missing=True)
        except Exception as exc:  # pygltflib raises whatever its JSON decoding hits
            self.fail("JSON chunk", f"expected glTF 2.0 JSON ({type(exc).__name__}: {exc})")
        version = getattr(self.gltf.asset, "version", None)
        if version != "2.0":
            self.fail("asset.version", f"expected '2.0', got {version!r}")
        extensions = self.gltf.extensions if isinstance(self.gltf.extensions, dict) else {}
        if EXTENSION not in extensions:
            self.fail(f"extensions.{EXTENSION}", "missing: this glTF file is not a fae FaceModel")
        self.ext = extensions[EXTENSION]
        self.views = self.gltf.bufferViews or []

    def fail(self, field: str, message: str):
        raise FaceModelError(f"{self.name}: {field}: {message}")

    def _chunks(self, data: bytes) -> tuple[bytes, bytes]:
        if len(data) < 12 or data[:4] != _GLB_MAGIC:
            self.fail("header", "expected a binary glTF (.glb) file starting with 'glTF'")
        version, length = struct.unpack_from("<II", data, 4)
        if version != 2:
            self.fail("header.version", f"expected GLB container version 2, got {version}")
        if length > len(data):
            self.fail("header.length", f"file is truncated: header says {length} bytes, found {len(data)}")
        chunks: list[tuple[int, bytes]] = []
        offset = 12
        while offset < length:
            if offset + 8 > length:
                self.fail(f"chunk {len(chunks)}", "truncated chunk header")
            size, kind = struct.unpack_from("<II", data, offset)
            if offset + 8 + size > length:
                self.fail(f"chunk {len(chunks)}", f"file is truncated: chunk needs {size} bytes, {length - offset - 8} remain")
            chunks.append((kind, data[offset + 8 : offset + 8 + size]))
            offset += 8 + size
        if not chunks or chunks[0][0] != _CHUNK_JSON:
            self.fail("chunk 0", "expected the JSON chunk first")
        binary = next((c for k, c in chunks[1:] if k == _CHUNK_BIN), b"")
        return chunks[0][1], binary

    # typed access to the extension JSON ---------------------------------------------
    def get(self, obj, key: str, field: str, types, optional: bool = False):
        if not isinstance(obj, dict):
            self.fail(field.rsplit(".", 1)[0], "expected a JSON object")
        if key not in obj:
            self.fail(field, "missing")
        value = obj[key]
        if value is None and optional:
            return None
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in _as_tuple(types)):
            self.fail(field, f"expected {_type_names(types)}, got {type(value).__name__}")
        return value

    def numbers(self, values, field: str, shape: tuple, dtype) -> np.ndarray:
        try:
            array = np.array(values, dtype=dtype)
        except (TypeError, ValueError):
            self.fail(field, f"expected numbers of shape {shape}")
        if array.shape != shape or array.dtype.kind != np.dtype(dtype).kind or not _all_numbers(values):
            self.fail(field, f"expected numbers of shape {shape}")
        return array

    def array(self, record, field: str) -> np.ndarray:
        """Decode a {"dtype", "shape", "bufferView"} record into a fresh ndarray."""
        if not isinstance(record, dict):
            self.fail(field, "expected an array record {dtype, shape, bufferView}")
        text = self.get(record, "dtype", f"{field}.dtype", str)
        try:
            dtype = np.dtype(text)
        except TypeError:
            dtype = None
        if dtype is None or dtype.kind in "OV" or dtype.str != text:
            self.fail(f"{field}.dtype", f"expected a NumPy type string such as '<f8', got {text!r}")
        shape = self.get(record, "shape", f"{field}.shape", list)
        if not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
            self.fail(f"{field}.shape", f"expected a list of non-negative ints, got {shape!r}")
        nbytes = dtype.itemsize * math.prod(shape)
        if nbytes == 0:
            return np.zeros(shape, dtype=dtype)
        index = self.get(record, "bufferView", f"{field}.bufferView", int)
        if not 0 <= index < len(self.views):
            self.fail(f"{field}.bufferView", f"expected a buffer view index in [0, {len(self.views)}), got {index}")
        view = self.views[index]
        start = view.byteOffset or 0
        if not isinstance(start, int) or isinstance(start, bool) or start < 0:
            self.fail(f"bufferViews[{index}].byteOffset", f"expected a byte offset >= 0, got {start!r} (for {field})")
        if view.buffer != 0 or view.byteLength != nbytes or start + nbytes > len(self.blob):
            self.fail(
                f"{field}.bufferView",
                f"buffer view {index} holds {view.byteLength} bytes at offset {start} of a {len(self.blob)}-byte buffer; "
                f"expected {nbytes} bytes for {dtype.str} {tuple(shape)}",
            )
        return np.frombuffer(self.blob, dtype=dtype, count=math.prod(shape), offset=start).reshape(shape).copy()

    def surface_point(self, obj, field: str) -> SurfacePoint:
        return SurfacePoint(
            part=self.get(obj, "part", f"{field}.part", str),
            triangle=self.get(obj, "triangle", f"{field}.triangle", int),
            bary=self.numbers(self.get(obj, "bary", f"{field}.bary", list), f"{field}.bary", (3,), np.float64),
        )

    def check_node(self, node, field: str, vertex_count: int, face_count: int, also: int | None = None) -> None:
        """The render mesh of a surface must match its engine arrays (`also`: another vertex
        count it may have, the textured skin's without its seam copies)."""
        if node is None:
            return
        if not isinstance(node, int) or isinstance(node, bool) or not 0 <= node < len(self.gltf.nodes):
            self.fail(f"{field}.node", f"expected a node index in [0, {len(self.gltf.nodes)}), got {node!r}")
        mesh = self.gltf.nodes[node].mesh
        try:
            primitive = self.gltf.meshes[mesh].primitives[0]
            positions = self.gltf.accessors[primitive.attributes.POSITION].count
            indices = self.gltf.accessors[primitive.indices].count
        except (IndexError, TypeError, AttributeError):
            self.fail(f"{field}.node", f"node {node} has no triangle mesh with POSITION and indices")
        if positions not in (vertex_count, also) or indices != 3 * face_count:
            self.fail(
                f"{field}.node",
                f"render mesh of node {node} has {positions} vertices and {indices} indices; "
                f"expected {vertex_count} and {3 * face_count} (the file was edited inconsistently)",
            )

    # the model -----------------------------------------------------------------------
    def model(self) -> FaceModel:
        e = self.ext
        X = EXTENSION
        if not isinstance(e, dict):
            self.fail(X, "expected a JSON object")
        version = self.get(e, "version", f"{X}.version", int)
        if version != FORMAT_VERSION:
            self.fail(f"{X}.version", f"this reader knows version {FORMAT_VERSION}, the file has version {version}")

        s = self.get(e, "skin", f"{X}.skin", dict)
        skin_vertices = self.array(self.get(s, "vertices", f"{X}.skin.vertices", dict), f"{X}.skin.vertices")
        skin_faces = self.array(self.get(s, "faces", f"{X}.skin.faces", dict), f"{X}.skin.faces")
        skin_uv = self.array(self.get(s, "uv", f"{X}.skin.uv", dict), f"{X}.skin.uv")
        seam_copies = 0
        if (s.get("texture") is not None and skin_uv.shape == (len(skin_vertices), 2) and skin_faces.ndim == 2
                and skin_faces.size and 0 <= skin_faces.min() and skin_faces.max() < len(skin_vertices)):
            seam_copies = len(wrapped_seam(skin_faces, skin_uv)[1])  # the render mesh repeats the seam's vertices
        self.check_node(s.get("node"), f"{X}.skin", len(skin_vertices) + seam_copies, len(skin_faces),
                        also=len(skin_vertices))

        parts = {}
        for name, p in self.get(e, "parts", f"{X}.parts", dict).items():
            f = f"{X}.parts.{name}"
            vertex_colors = self.get(p, "vertex_colors", f"{f}.vertex_colors", dict, optional=True)
            part = Part(
                vertices=self.array(self.get(p, "vertices", f"{f}.vertices", dict), f"{f}.vertices"),
                faces=self.array(self.get(p, "faces", f"{f}.faces", dict), f"{f}.faces"),
                color=self.numbers(self.get(p, "color", f"{f}.color", list), f"{f}.color", (4,), np.float32),
                bone=self.get(p, "bone", f"{f}.bone", str),
                vertex_colors=None if vertex_colors is None else self.array(vertex_colors, f"{f}.vertex_colors"),
            )
            self.check_node(p.get("node"), f, len(part.vertices), len(part.faces))
            parts[name] = part

        jaw = self.get(e, "jaw", f"{X}.jaw", dict)
        muscles = []
        for i, mu in enumerate(self.get(e, "muscles", f"{X}.muscles", list)):
            f = f"{X}.muscles[{i}]"
            insertion = self.get(mu, "insertion", f"{f}.insertion", dict, optional=True)
            semi_axes = self.get(mu, "semi_axes", f"{f}.semi_axes", list, optional=True)
            axes = self.get(mu, "axes", f"{f}.axes", list, optional=True)
            muscles.append(
                Muscle(
                    name=self.get(mu, "name", f"{f}.name", str),
                    kind=self.get(mu, "kind", f"{f}.kind", str),
                    attachment=self.surface_point(self.get(mu, "attachment", f"{f}.attachment", dict), f"{f}.attachment"),
                    insertion=None if insertion is None else self.surface_point(insertion, f"{f}.insertion"),
                    regions=self.strings(self.get(mu, "regions", f"{f}.regions", list), f"{f}.regions"),
                    zone_angle=float(self.get(mu, "zone_angle", f"{f}.zone_angle", (int, float))),
                    fall_start=float(self.get(mu, "fall_start", f"{f}.fall_start", (int, float))),
                    fall_end=float(self.get(mu, "fall_end", f"{f}.fall_end", (int, float))),
                    semi_axes=None if semi_axes is None else self.numbers(semi_axes, f"{f}.semi_axes", (2,), np.float64),
                    axes=None if axes is None else self.numbers(axes, f"{f}.axes", (2, 3), np.float64),
                )
            )

        tables = []
        for i, t in enumerate(self.get(e, "face_def_tables", f"{X}.face_def_tables", list)):
            f = f"{X}.face_def_tables[{i}]"
            tables.append(
                FaceDefTable(
                    fap=self.get(t, "fap", f"{f}.fap", int),
                    part=self.get(t, "part", f"{f}.part", str),
                    vertices=self.array(self.get(t, "vertices", f"{f}.vertices", dict), f"{f}.vertices"),
                    borders=self.array(self.get(t, "borders", f"{f}.borders", dict), f"{f}.borders"),
                    displacements=self.array(self.get(t, "displacements", f"{f}.displacements", dict), f"{f}.displacements"),
                    source=self.get(t, "source", f"{f}.source", str) if "source" in t else "authored",
                )
            )

        return FaceModel(
            skin_vertices=skin_vertices,
            skin_faces=skin_faces,
            skin_uv=skin_uv,
            skin_color=self.numbers(self.get(s, "color", f"{X}.skin.color", list), f"{X}.skin.color", (4,), np.float32),
            skin_mirror=self.array(self.get(s, "mirror", f"{X}.skin.mirror", dict), f"{X}.skin.mirror"),
            skin_region=self.array(self.get(s, "region", f"{X}.skin.region", dict), f"{X}.skin.region"),
            region_names=self.strings(self.get(e, "region_names", f"{X}.region_names", list), f"{X}.region_names"),
            skin_thickness=self.array(self.get(s, "thickness", f"{X}.skin.thickness", dict), f"{X}.skin.thickness"),
            layer_params=self.get(e, "layer_params", f"{X}.layer_params", dict),
            parts=parts,
            jaw_pivot=self.numbers(self.get(jaw, "pivot", f"{X}.jaw.pivot", list), f"{X}.jaw.pivot", (3,), np.float64),
            jaw_axis=self.numbers(self.get(jaw, "axis", f"{X}.jaw.axis", list), f"{X}.jaw.axis", (3,), np.float64),
            eye_centers={
                key: self.numbers(c, f"{X}.eye_centers.{key}", (3,), np.float64)
                for key, c in self.get(e, "eye_centers", f"{X}.eye_centers", dict).items()
            },
            feature_points={
                key: self.surface_point(p, f"{X}.feature_points.{key}")
                for key, p in self.get(e, "feature_points", f"{X}.feature_points", dict).items()
            },
            muscles=muscles,
            face_def_tables=tables,
            fap_mapping={
                key: self.array(r, f"{X}.fap_mapping.{key}") for key, r in self.get(e, "fap_mapping", f"{X}.fap_mapping", dict).items()
            },
            scan_transform=self.numbers(self.get(e, "scan_transform", f"{X}.scan_transform", list), f"{X}.scan_transform", (4, 4), np.float64),
            meta=self.get(e, "meta", f"{X}.meta", dict),
            skin_texture=self.texture(s.get("texture"), f"{X}.skin.texture"),
        )

    def texture(self, record, field: str) -> np.ndarray | None:
        """The skin's texture (H, W, 3) uint8 from {"image": index}, or None."""
        if record is None:
            return None
        index = self.get(record, "image", f"{field}.image", int)
        images = self.gltf.images or []
        if not 0 <= index < len(images):
            self.fail(f"{field}.image", f"expected an image index in [0, {len(images)}), got {index}")
        view_index = images[index].bufferView
        if not isinstance(view_index, int) or not 0 <= view_index < len(self.views):
            self.fail(f"images[{index}].bufferView", "expected the image inside the binary chunk")
        view = self.views[view_index]
        start = view.byteOffset or 0
        data = self.blob[start:start + view.byteLength]
        try:
            return png_pixels(data)
        except ValueError as exc:
            self.fail(f"images[{index}]", str(exc))

    def strings(self, values: list, field: str) -> list[str]:
        if not all(isinstance(v, str) for v in values):
            self.fail(field, "expected a list of strings")
        return list(values)


def _as_tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)


def _type_names(types) -> str:
    names = {dict: "a JSON object", list: "a JSON array", str: "a string", int: "an integer", float: "a number"}
    return " or ".join(names.get(t, t.__name__) for t in _as_tuple(types))


def _all_numbers(values) -> bool:
    if isinstance(values, list):
        return all(_all_numbers(v) for v in values)
    return isinstance(values, (int, float)) and not isinstance(values, bool)
