"""The FaceModel .glb format: exact round trips, viewer compatibility, clear errors."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fae.io.facemodel import FaceModel, SurfacePoint
from fae.io.facemodel_gltf import (
    EXTENSION,
    FaceModelError,
    facemodel_from_glb,
    facemodel_to_glb,
    read_facemodel,
    structural_problems,
    write_facemodel,
)
from fae.data import shipped_head_path
from fae.mpeg4 import FEATURE_POINTS
from synthetic_head import fdp_names_from_group_sizes, synthetic_head

REPO = Path(__file__).resolve().parent.parent
TEMPLATE = shipped_head_path()
VALIDATOR = REPO / "tools" / "node_modules" / "gltf-validator"
SURFACES = ["skin", "cranium", "mandible", "upper_teeth", "lower_teeth", "tongue", "eye_l", "eye_r"]


@pytest.fixture(scope="module")
def head() -> FaceModel:
    return synthetic_head()


@pytest.fixture(scope="module")
def head_file(head, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("facemodel") / "head.glb"
    write_facemodel(head, path)
    return path


# -- helpers ------------------------------------------------------------------------------


def assert_same(a, b, where: str = "model") -> None:
    """Field-by-field equality: arrays bit-identical with the same dtype, containers equal."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray), where
        assert a.dtype == b.dtype, f"{where}: dtype {a.dtype} != {b.dtype}"
        assert a.shape == b.shape, f"{where}: shape {a.shape} != {b.shape}"
        assert a.tobytes() == b.tobytes(), f"{where}: values differ"
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), f"{where}: keys {list(a)} != {list(b)}"
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert type(a) is type(b) and a == b, f"{where}: {a!r} != {b!r}"


def split_glb(data: bytes) -> tuple[dict, bytes]:
    json_length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20 : 20 + json_length])
    return document, data[20 + json_length :]


def join_glb(document: dict, rest: bytes) -> bytes:
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 8)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + rest
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def validate(path: Path) -> dict:
    """The Khronos glTF validator's JSON report on `path` (skips without node or the validator)."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: cannot run the Khronos glTF validator")
    if not VALIDATOR.is_dir():
        pytest.skip("tools/node_modules/gltf-validator is missing (run `make install`)")
    result = subprocess.run([node, str(REPO / "tests" / "validate_gltf.mjs"), str(path)], capture_output=True, text=True, timeout=300)
    assert result.returncode in (0, 1), result.stderr
    return json.loads(result.stdout)


# -- round trips --------------------------------------------------------------------------


def test_read_returns_exactly_what_was_written(head, head_file):
    assert_same(head, read_facemodel(head_file))


def test_rewriting_a_read_file_reproduces_its_bytes(head_file, tmp_path):
    again = tmp_path / "again.glb"
    write_facemodel(read_facemodel(head_file), again)
    assert again.read_bytes() == head_file.read_bytes()


def test_output_is_deterministic(head, head_file):
    assert facemodel_to_glb(copy.deepcopy(head)) == head_file.read_bytes()


def test_writing_does_not_modify_the_model(head):
    before = copy.deepcopy(head)
    facemodel_to_glb(head)
    assert_same(before, head)


def test_round_trip_of_a_template_head_without_parts_colours_or_tables(tmp_path):
    model = synthetic_head(personalized=False)
    model.face_def_tables = []
    model.fap_mapping = {}
    model.meta = {}
    model.parts["eye_l"].vertex_colors = None
    path = tmp_path / "template.glb"
    write_facemodel(model, path)
    back = read_facemodel(path)
    assert_same(model, back)
    assert np.array_equal(back.scan_transform, np.eye(4))


def test_round_trip_of_a_real_face_mesh_as_skin(head, tmp_path):
    obj = REPO.parent / "shared" / "data" / "heads" / "mediapipe_canonical" / "canonical_face_model.obj"
    if not obj.is_file():
        pytest.skip(f"test data {obj} is absent")
    import trimesh

    mesh = trimesh.load(obj, process=False, force="mesh")
    model = copy.deepcopy(head)
    model.skin_vertices = np.asarray(mesh.vertices, dtype=np.float64) / 100.0  # cm -> m
    model.skin_faces = np.asarray(mesh.faces, dtype=np.int32)
    n = len(model.skin_vertices)
    model.skin_uv = np.asarray(mesh.visual.uv, dtype=np.float32)
    model.skin_mirror = np.arange(n, dtype=np.int32)
    model.skin_region = np.zeros(n, dtype=np.int32)
    model.skin_thickness = np.full(n, 0.005)
    model.face_def_tables = []
    path = tmp_path / "mediapipe.glb"
    write_facemodel(model, path, check=False)  # feature points still refer to the sphere's triangles
    assert_same(model, read_facemodel(path, check=False))


# -- what viewers see ---------------------------------------------------------------------


def test_khronos_validator_reports_no_errors(head, head_file):
    report = validate(head_file)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    assert report["info"]["totalVertexCount"] == sum(len(head.mesh(name)[0]) for name in SURFACES)


def test_trimesh_opens_it_as_a_lit_coloured_scene_in_metres(head, head_file):
    import trimesh

    scene = trimesh.load(head_file)
    assert isinstance(scene, trimesh.Scene)
    assert sorted(scene.geometry) == sorted(SURFACES)
    skin = scene.geometry["skin"]
    assert np.allclose(skin.vertices, head.skin_vertices, atol=1e-6)
    assert np.array_equal(skin.faces, head.skin_faces)
    size = scene.bounds[1] - scene.bounds[0]
    assert np.all((0.1 < size) & (size < 0.5)), f"a head is decimetres wide, got {size} m"
    material = skin.visual.material
    assert np.allclose(np.asarray(material.baseColorFactor[:3]) / 255.0, head.skin_color[:3], atol=1 / 255)
    assert material.roughnessFactor == pytest.approx(0.6)
    # smooth normals point outwards on the convex skin
    outward = np.einsum("ij,ij->i", skin.vertex_normals, skin.vertices - skin.vertices.mean(axis=0))
    assert np.all(outward > 0)


def test_render_accessors_and_extension_are_declared_for_viewers(head_file):
    document, _ = split_glb(head_file.read_bytes())
    assert document["extensionsUsed"] == [EXTENSION]
    assert EXTENSION not in document.get("extensionsRequired", [])
    names = [node["name"] for node in document["nodes"]]
    assert names == SURFACES
    skin = document["meshes"][0]["primitives"][0]
    assert {"POSITION", "NORMAL", "TEXCOORD_0"} <= set(skin["attributes"])
    eye = document["meshes"][names.index("eye_l")]["primitives"][0]
    assert "COLOR_0" in eye["attributes"]
    assert document["extensions"][EXTENSION]["version"] == 1


def test_fapu_are_stored_for_other_readers(head, head_file):
    document, _ = split_glb(head_file.read_bytes())
    fapu = document["extensions"][EXTENSION]["fapu"]
    p = head.feature_point_positions()
    assert fapu["MW"] == pytest.approx((p["8.3"][0] - p["8.4"][0]) / 1024)
    assert fapu["ES"] == pytest.approx((p["3.5"][0] - p["3.6"][0]) / 1024)
    assert fapu["AU"] == 1e-5


def test_a_failed_write_leaves_the_previous_file_untouched(head, head_file, tmp_path):
    target = tmp_path / "head.glb"
    shutil.copyfile(head_file, target)
    model = copy.deepcopy(head)
    model.meta = {"bad": object()}
    with pytest.raises(FaceModelError, match="meta"):
        write_facemodel(model, target, check=False)
    model.skin_vertices = model.skin_vertices.copy()
    model.skin_vertices[0, 0] = np.nan
    model.meta = {}
    with pytest.raises(FaceModelError, match="head.glb"):
        write_facemodel(model, target, check=False)
    assert target.read_bytes() == head_file.read_bytes()
    assert [p.name for p in tmp_path.iterdir()] == ["head.glb"]


# -- reading bad files --------------------------------------------------------------------


def expect_error(tmp_path: Path, data: bytes, *fields: str) -> str:
    path = tmp_path / "bad.glb"
    path.write_bytes(data)
    with pytest.raises(FaceModelError) as info:
        read_facemodel(path)
    message = str(info.value)
    assert str(path) in message
    for f in fields:
        assert f in message
    return message


def test_a_file_that_is_not_gltf(tmp_path):
    expect_error(tmp_path, b"ply\nformat ascii 1.0\nend_header\n", "header", "glTF")


def test_a_text_gltf_is_refused_as_not_binary(tmp_path):
    expect_error(tmp_path, b'{"asset": {"version": "2.0"}}', "header")


def test_a_gltf_without_the_extension_is_not_a_facemodel(tmp_path):
    import trimesh

    plain = trimesh.creation.box().export(file_type="glb")
    expect_error(tmp_path, plain, EXTENSION, "not a fae FaceModel")


def test_a_truncated_file(tmp_path, head_file):
    data = head_file.read_bytes()
    for cut in (8, 30, len(data) // 2, len(data) - 1):
        expect_error(tmp_path, data[:cut], "truncated" if cut > 12 else "header")


def test_a_missing_file_names_the_path(tmp_path):
    with pytest.raises(FaceModelError, match="nowhere.glb"):
        read_facemodel(tmp_path / "nowhere.glb")


def test_an_array_record_that_does_not_match_its_buffer_view(tmp_path, head_file):
    document, rest = split_glb(head_file.read_bytes())
    document["extensions"][EXTENSION]["skin"]["thickness"]["shape"] = [5]
    expect_error(tmp_path, join_glb(document, rest), "skin.thickness.bufferView", "expected 40 bytes")


def test_a_bad_dtype_string(tmp_path, head_file):
    document, rest = split_glb(head_file.read_bytes())
    document["extensions"][EXTENSION]["skin"]["region"]["dtype"] = "object"
    expect_error(tmp_path, join_glb(document, rest), "skin.region.dtype")


def test_a_missing_field(tmp_path, head_file):
    document, rest = split_glb(head_file.read_bytes())
    del document["extensions"][EXTENSION]["jaw"]["axis"]
    expect_error(tmp_path, join_glb(document, rest), "jaw.axis", "missing")


def test_a_field_of_the_wrong_type(tmp_path, head_file):
    document, rest = split_glb(head_file.read_bytes())
    document["extensions"][EXTENSION]["muscles"][0]["zone_angle"] = "wide"
    expect_error(tmp_path, join_glb(document, rest), "muscles[0].zone_angle", "number")


def test_a_newer_format_version(tmp_path, head_file):
    document, rest = split_glb(head_file.read_bytes())
    document["extensions"][EXTENSION]["version"] = 2
    expect_error(tmp_path, join_glb(document, rest), "version")


def test_an_out_of_range_triangle_in_the_file(tmp_path, head_file):
    document, rest = split_glb(head_file.read_bytes())
    document["extensions"][EXTENSION]["feature_points"]["2.1"]["triangle"] = 99999
    message = expect_error(tmp_path, join_glb(document, rest), "feature_points['2.1'].triangle")
    assert read_facemodel(tmp_path / "bad.glb", check=False).feature_points["2.1"].triangle == 99999, message


def test_a_render_mesh_edited_out_of_step_with_the_engine_arrays(tmp_path, head_file):
    document, rest = split_glb(head_file.read_bytes())
    document["accessors"][document["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["count"] -= 1
    expect_error(tmp_path, join_glb(document, rest), "skin.node", "edited")


# -- structural problems ------------------------------------------------------------------


def test_fdp_names_are_the_standard_84():
    names = fdp_names_from_group_sizes()
    assert len(names) == 84
    assert [p.name for p in FEATURE_POINTS] == names


def test_a_good_model_has_no_structural_problems(head):
    assert structural_problems(head) == []
    assert structural_problems(head, fdp_names=fdp_names_from_group_sizes()) == []


def seeded(head: FaceModel, defect) -> list[str]:
    model = copy.deepcopy(head)
    defect(model)
    return structural_problems(model)


def test_structural_problems_finds_seeded_defects(head):
    def out_of_range_triangle(m):
        m.feature_points["2.1"].triangle = len(m.skin_faces)

    def bad_barycentric(m):
        m.muscles[0].insertion.bary = np.array([0.7, 0.7, -0.4])

    def missing_fdp(m):
        del m.feature_points["9.15"]

    def non_unit_jaw_axis(m):
        m.jaw_axis = np.array([1.0, 0.1, 0.0])

    def face_index_out_of_range(m):
        m.parts["tongue"].faces = m.parts["tongue"].faces.copy()
        m.parts["tongue"].faces[0, 0] = len(m.parts["tongue"].vertices)

    def decreasing_borders(m):
        m.face_def_tables[1].borders = m.face_def_tables[1].borders[::-1].copy()

    def wrong_displacement_shape(m):
        m.face_def_tables[0].displacements = np.zeros((1, 4, 3))

    def unknown_muscle_kind(m):
        m.muscles[2].kind = "circular"

    def wrong_dtype(m):
        m.skin_faces = m.skin_faces.astype(np.int64)

    def surface_point_on_unknown_part(m):
        m.feature_points["3.5"] = SurfacePoint("eyebrow", 0, np.array([1.0, 0.0, 0.0]))

    def broken_mirror(m):
        m.skin_mirror = np.roll(m.skin_mirror, 1)

    def numpy_scalar_in_meta(m):
        m.meta["count"] = np.int64(3)

    expected = {
        out_of_range_triangle: "feature_points['2.1'].triangle",
        bad_barycentric: "muscles[0] (zygomatic_major_l).insertion.bary",
        missing_fdp: "missing 9.15",
        non_unit_jaw_axis: "jaw_axis: expected a unit vector",
        face_index_out_of_range: "parts['tongue'].faces",
        decreasing_borders: "face_def_tables[1].borders: expected strictly increasing",
        wrong_displacement_shape: "face_def_tables[0].displacements: expected shape (1, 5, 3)",
        unknown_muscle_kind: "muscles[2] (orbicularis_oris).kind",
        wrong_dtype: "skin_faces: expected dtype int32",
        surface_point_on_unknown_part: "feature_points['3.5'].part",
        broken_mirror: "skin_mirror",
        numpy_scalar_in_meta: "meta['count']",
    }
    for defect, text in expected.items():
        problems = seeded(head, defect)
        assert len(problems) == 1 and text in problems[0], (defect.__name__, problems)


def test_writing_refuses_an_inconsistent_model_and_names_the_problem(head, tmp_path):
    model = copy.deepcopy(head)
    model.jaw_axis = np.array([0.0, 0.0, 0.0])
    target = tmp_path / "head.glb"
    with pytest.raises(FaceModelError, match=r"head\.glb.*jaw_axis"):
        write_facemodel(model, target)
    assert not target.exists()


# -- the shipped template -----------------------------------------------------------------


@pytest.mark.slow
def test_shipped_template_round_trips_and_validates(tmp_path):
    if not TEMPLATE.is_file():
        pytest.skip(f"{TEMPLATE} is not built yet")
    model = read_facemodel(TEMPLATE)
    again = tmp_path / "generic_head.glb"
    write_facemodel(model, again)  # bytes may differ from the committed file's (pygltflib, normals)
    assert_same(model, read_facemodel(again))
    report = validate(TEMPLATE)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]


# -- any corruption gives FaceModelError ------------------------------------------------------

@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_corrupted_bytes_raise_facemodel_error_or_decode(head_file, data):
    original = head_file.read_bytes()
    json_end = 20 + struct.unpack_from("<I", original, 12)[0]
    corrupted = bytearray(original)
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, json_end + 64))  # mostly the header and the JSON chunk
        corrupted[at] = data.draw(st.integers(0, 255))
    if data.draw(st.booleans()):
        corrupted = corrupted[: data.draw(st.integers(0, len(corrupted)))]
    try:
        model = facemodel_from_glb(bytes(corrupted), name="corrupt.glb")
    except FaceModelError as exc:
        assert "corrupt.glb" in str(exc)
    else:
        assert structural_problems(model) == []


# -- a textured skin -----------------------------------------------------------------------


def textured(head: FaceModel) -> FaceModel:
    """The head with a cylindrical texture map and a colour ramp for a texture."""
    from fae.anatomy.template import skin_uv

    out = copy.deepcopy(head)
    out.skin_uv = skin_uv(out.skin_vertices)
    rows, cols = np.mgrid[0:64, 0:128]
    out.skin_texture = np.stack([2 * cols, 4 * rows, 255 - 2 * cols], axis=2).astype(np.uint8)
    return out


def test_a_texture_comes_back_exactly_and_viewers_see_it(head, tmp_path):
    model = textured(head)
    path = tmp_path / "textured.glb"
    write_facemodel(model, path)
    again = read_facemodel(path)
    assert_same(model, again)
    document, _ = split_glb(path.read_bytes())
    skin_material = document["materials"][document["meshes"][0]["primitives"][0]["material"]]
    assert skin_material["pbrMetallicRoughness"]["baseColorTexture"]["index"] == 0
    assert document["images"][0]["mimeType"] == "image/png"
    assert validate(path)["issues"]["numErrors"] == 0


def test_a_texture_that_is_not_an_rgb_image_is_named(head):
    model = textured(head)
    model.skin_texture = model.skin_texture.astype(np.float32)
    assert any(p.startswith("skin_texture") for p in structural_problems(model))
    with pytest.raises(FaceModelError, match="skin_texture"):
        facemodel_to_glb(model)


def test_the_exported_scene_carries_the_texture_across_the_seam(head, tmp_path):
    """`fae export`'s scene: the skin's triangles that cross the texture's seam get their own
    copies of its vertices (u + 1), in the mesh and in its morph targets, and the file
    passes the validator."""
    from fae.io.export_gltf import scene_glb
    from fae.mesh import wrapped_seam

    model = textured(head)
    n = len(model.skin_vertices)

    class Target:
        name = "lift"
        vertices = np.arange(0, n, 3)
        displacement = np.tile([0.0, 0.001, 0.0], (len(vertices), 1))

    _, source, _ = wrapped_seam(model.skin_faces, model.skin_uv)
    assert len(source) > 0  # the synthetic head's map has a seam
    path = tmp_path / "scene.glb"
    path.write_bytes(scene_glb(model, targets=[Target()]))
    document, _ = split_glb(path.read_bytes())
    skin = next(m for m in document["meshes"] if m["name"] == "skin")["primitives"][0]
    assert document["accessors"][skin["attributes"]["POSITION"]]["count"] == n + len(source)
    assert "TEXCOORD_0" in skin["attributes"]
    sparse = document["accessors"][skin["targets"][0]["POSITION"]]["sparse"]
    assert sparse["count"] == len(Target.vertices) + int(np.isin(source, Target.vertices).sum())
    assert validate(path)["issues"]["numErrors"] == 0
