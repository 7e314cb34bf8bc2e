"""`fae adapt` against inputs it cannot fit and fits no one should animate: each is one
line naming the file or the measure, exit 2, no traceback, nothing written; reports stay
valid JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from fae.adapt.synthetic import synthetic_scan
from fae.cli import main
from fae.commands.adapt_checks import implausible_fit


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory):
    """A synthetic face scan in millimetres (OBJ) and its feature points (JSON)."""
    d = tmp_path_factory.mktemp("scan")
    scan = synthetic_scan(0, subdivisions=4)
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(d / "face.obj")
    (d / "points.json").write_text(json.dumps({n: list(map(float, p)) for n, p in scan.landmarks.items()}))
    return d / "face.obj", d / "points.json", scan


def adapt(capsys, *args: str) -> tuple[int, str]:
    code = main(["adapt", *map(str, args), "--no-calibrate"])
    err = capsys.readouterr().err
    assert "Traceback" not in err and "numpy" not in err and "matmul" not in err
    return code, err


def one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("fae adapt: ")]
    assert len(lines) == 1, err
    return lines[0]


def test_an_output_that_is_an_input_is_refused_and_the_input_kept(scan_files, capsys, tmp_path, monkeypatch):
    """Case: `-o` equal to the scan overwrote the scan with a glTF file."""
    scan, points, _ = scan_files
    before = scan.read_bytes()
    monkeypatch.chdir(scan.parent)
    for args in ((scan, "-o", "./face.obj"), (scan, "-o", tmp_path / "h.glb", "--report", points, "--landmarks", points)):
        code, err = adapt(capsys, *args)
        assert code == 2 and "expected a new file (inputs are never overwritten)" in one_line(err)
    assert scan.read_bytes() == before and json.loads(points.read_text())


@pytest.mark.parametrize("name, content, expected", [
    ("one.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "1 of its 1 triangles have an area; expected a head scan"),
    ("flat.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 0 0\nf 1 2 3\nf 1 4 2\nf 1 1 2\n",
     "0 of its 3 triangles have an area; expected a head scan"),
    ("noise.obj", bytes(np.random.default_rng(3).integers(0, 256, 5000, dtype=np.uint8)),
     "cannot read a mesh: expected a mesh file (OBJ, PLY, STL, OFF, GLB/glTF)"),
    ("noise.ply", bytes(np.random.default_rng(4).integers(0, 256, 5000, dtype=np.uint8)),
     "expected a mesh file (OBJ, PLY, STL, OFF, GLB/glTF)"),
    ("huge.obj", "v 1e200 0 0\nv 0 1e200 0\nv 0 0 1e200\nv 1e200 1e200 1e200\nf 1 2 3\nf 1 2 4\nf 2 3 4\n",
     "coordinates up to 1e+200; expected a head scan in some unit of length"),
])
def test_meshes_that_are_no_head_scan_are_one_line_naming_the_file(tmp_path, capsys, name, content, expected):
    """Case: a one-triangle mesh and degenerate triangles failed in numpy's matmul, a
    random-bytes mesh with "No module named 'charset_normalizer'"; coordinates of 1e200 gave
    eight lines of numpy's overflow warnings, then "0 triangles have an area"."""
    path = tmp_path / name
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    code, err = adapt(capsys, path, "-o", tmp_path / "h.glb")
    assert code == 2 and one_line(err).startswith(f"fae adapt: {path}") and expected in err
    assert not (tmp_path / "h.glb").exists()


def test_many_degenerate_triangles_are_no_surface(tmp_path, capsys):
    V = np.random.default_rng(1).normal(size=(500, 3))
    F = np.array([[i, i, i + 1] for i in range(499)])
    path = tmp_path / "slivers.obj"
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in V) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))
    code, err = adapt(capsys, path, "-o", tmp_path / "h.glb")
    assert code == 2 and "0 of its 499 triangles have an area" in one_line(err)


@pytest.mark.parametrize("scale, unit", [(1e-3, "metres"), (0.1, "centimetres")])
def test_feature_points_in_another_unit_than_the_scan_are_named(scan_files, tmp_path, capsys, scale, unit):
    scan, _, synthetic = scan_files
    points = tmp_path / f"{unit}.json"
    points.write_text(json.dumps({n: list(map(float, p * scale)) for n, p in synthetic.landmarks.items()}))
    code, err = adapt(capsys, scan, "--landmarks", points, "-o", tmp_path / "h.glb")
    line = one_line(err)
    assert code == 2 and line.startswith(f"fae adapt: {points}: the feature points lie ")
    assert "expected points on the scan, in its unit and frame" in line


def test_null_and_nan_feature_points_are_named_not_dropped(scan_files, tmp_path, capsys):
    """Case: 34 of 68 null points were dropped silently and the fit went on (exit 0)."""
    scan, _, _ = scan_files
    points = [[float(i), 0.0, 0.0] for i in range(68)]
    for i in range(0, 68, 2):
        points[i] = [None, None, None]
    ljson = tmp_path / "nulls.ljson"
    ljson.write_text(json.dumps({"groups": {"dlib": {"landmarks": {"points": points}}}}))
    code, err = adapt(capsys, scan, "--landmarks", ljson, "-o", tmp_path / "h.glb")
    assert code == 2 and "iBUG points are null or not finite (0-based: 8, 22, 24" in one_line(err)
    csv = tmp_path / "nan.csv"
    csv.write_text("name,x,y,z\n9.3,nan,1,2\n")
    code, err = adapt(capsys, scan, "--landmarks", csv, "-o", tmp_path / "h.glb")
    assert code == 2 and one_line(err) == f"fae adapt: {csv}: line 2: x, y, z must be finite numbers, got nan, 1, 2"
    named = tmp_path / "named.json"
    named.write_text('{"9.3": [NaN, 1, 2]}')
    code, err = adapt(capsys, scan, "--landmarks", named, "-o", tmp_path / "h.glb")
    assert code == 2 and "field '9.3': expected [x, y, z] (3 finite numbers)" in one_line(err)


def test_implausible_transfers_and_infinite_errors_are_reasons_to_refuse():
    good = {"fapu_ratio": 1.05, "eye_scale": {"eye_l": 1.02, "eye_r": 1.04},
            "errors": {"face_to_scan_rms_rel": 0.001}}
    assert implausible_fit(good) == []
    cases = {
        "eye_scale 8492": ({"eye_scale": {"eye_l": 8492.0, "eye_r": 8492.0}}, "eye_l is scaled 8.49e+03"),
        "one eye shrunk": ({"eye_scale": {"eye_l": 0.45, "eye_r": 1.0}}, "the eyeballs are scaled unlike each other"),
        "tiny FAPU": ({"fapu_ratio": 0.1}, "the face's FAPU are 0.1 times the template's"),
        "infinite error": ({"final": {"model_to_scan_rms": math.inf, "marker_error": 0.001}},
                           "final error model_to_scan_rms not finite"),
    }
    for name, (change, expected) in cases.items():
        reasons = implausible_fit({**good, **change})
        assert any(expected in r for r in reasons), (name, reasons)


@pytest.mark.slow
def test_a_partial_scan_is_refused_and_its_report_is_valid_json(shared_data, tmp_path, capsys):
    """Case: a scan with one face in twelve fitted with exit 0, model->scan RMS `inf`, and
    a report holding `Infinity` (not JSON)."""
    menpo = shared_data / "heads" / "menpo3d_template"
    mesh = trimesh.load(menpo / "template.ply", process=False)
    partial = tmp_path / "partial.ply"
    trimesh.Trimesh(mesh.vertices, mesh.faces[::12], process=False).export(partial)
    report = tmp_path / "r.json"
    code, err = adapt(capsys, partial, "--method", "multilevel", "--landmarks", menpo / "template.ljson",
                      "-o", tmp_path / "h.glb", "--report", report)
    assert code == 2 and "not finite (part of the model found no scan)" in err
    assert f"not writing {tmp_path / 'h.glb'}" in err and not (tmp_path / "h.glb").exists()

    def no_constants(token):
        raise AssertionError(f"report holds {token}")

    data = json.loads(report.read_text(), parse_constant=no_constants)
    assert data["verdict"] and data["final"]["model_to_scan_rms"] is None


def test_queries_keep_their_precision_far_from_the_origin():
    """Warp's BVH holds points in float32: a mesh 4,000 km from the file's origin (a
    survey's coordinates) was held in 0.25 m steps. About the mesh's own middle, a point
    1 mm off a 20 cm sphere there is found 1 mm off; and the closest points, taken from
    Warp's float32 weights, are those of the same sphere at the origin to a micrometre (the
    weights times coordinates 1e5 out were off by 0.5 mm: a bust's face "1 % off" its scan)."""
    import trimesh

    from fae.adapt.query import MeshQuery

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    offset = np.array([500_000.0, 4_000_000.0, 120.0])
    q = MeshQuery(sphere.vertices + offset, sphere.faces)
    direction = np.array([0.6, 0.0, 0.8])
    _, distance, face, _ = q.closest_points((0.101 * direction + offset)[None])
    assert face[0] >= 0 and abs(distance[0] - 0.001) < 2e-4
    X = np.random.default_rng(0).normal(size=(300, 3))
    X = 0.1 * X / np.linalg.norm(X, axis=1, keepdims=True) * np.random.default_rng(1).uniform(0.95, 1.05, (300, 1))
    here = MeshQuery(sphere.vertices, sphere.faces).closest_points(X)
    there = q.closest_points(X + offset)
    assert np.abs(there[1] - here[1]).max() < 1e-6 and np.abs(there[0] - offset - here[0]).max() < 1e-6


@pytest.mark.parametrize("extra, expected", [
    (["--plot", "{tmp}/p.png"], "--plot belongs to the paper methods"),
    (["--levels", "5", "--feature-search", "ga"], "--levels, --feature-search belong to the paper methods"),
    (["--method", "multilevel", "--levels", "50"], "--levels 50: expected 0-4"),
    (["--method", "multilevel", "--levels", "-3"], "--levels -3: expected 0-4"),
    (["--report", "{tmp}/r.png"], "--report {tmp}/r.png: expected a .json file name"),
    (["--compare", "{tmp}/c.jpg"], "--compare {tmp}/c.jpg: expected a .png file name"),
    (["--template", "{tmp}"], "is a folder, expected a FaceModel .glb"),
    (["--method", "rbf", "--landmarks", "{points}", "--feature-search", "ga"], "--landmarks gives them"),
])
def test_options_that_would_be_ignored_or_misnamed_are_refused_before_any_work(scan_files, capsys, tmp_path, extra,
                                                                               expected):
    """Cases: `--plot P.png` with the default fit wrote no plot without a word (--levels and
    --feature-search likewise did nothing); `--levels 50` ran past 11 GB; a report written
    as r.png, a picture as c.jpg; a folder given as the template was "not found"."""
    scan, points, _ = scan_files
    out = tmp_path / "h.glb"
    code, err = adapt(capsys, scan, "-o", out, *[a.format(tmp=tmp_path, points=points) for a in extra])
    assert code == 2 and expected.format(tmp=tmp_path) in one_line(err)
    assert list(tmp_path.iterdir()) == []
    code, err = adapt(capsys, scan, "-o", tmp_path / "h.txt")
    assert code == 2 and "expected a .glb file name" in one_line(err)


def test_feature_points_all_on_one_spot_are_refused_as_such(scan_files, capsys, tmp_path):
    """Case: every point given at the nose tip was refused as lying "a median of
    477232400493768349843456.0 mm" off the scan: the points coincide, and it says so."""
    scan, _, synthetic = scan_files
    points = tmp_path / "same.json"
    tip = list(map(float, synthetic.landmarks["9.3"]))
    points.write_text(json.dumps({n: tip for n in synthetic.landmarks}))
    code, err = adapt(capsys, scan, "--landmarks", points, "-o", tmp_path / "h.glb")
    assert code == 2 and "lie within 0 units of each other" in one_line(err) and "own place" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["same.json"]


def test_a_scan_doubled_back_to_back_is_refused_naming_its_winding(scan_files, capsys, tmp_path):
    """Case: a scan holding every face twice, once each way round (an exporter's 'double
    sided'), was fitted with the points given: the head came out with its eyes and mouth
    misshapen and a lump on the neck, exit 0."""
    _, points, synthetic = scan_files
    doubled = tmp_path / "doubled.ply"
    trimesh.Trimesh(synthetic.vertices, np.vstack([synthetic.faces, synthetic.faces[:, ::-1]]),
                    process=False).export(doubled)
    code, err = adapt(capsys, doubled, "--landmarks", points, "-o", tmp_path / "h.glb")
    assert code == 2 and "50 % of its area faces into it" in one_line(err) and "doubled back to back" in err
    assert not (tmp_path / "h.glb").exists()


def test_a_scan_in_no_unit_of_length_is_told_so(scan_files, capsys, tmp_path):
    """Case: a scan 7 units to a metre was taken in decimetres and gave a head 0.70x life
    size, said only in --report. The synthetic face in millimetres scaled by 0.8 is in no
    unit fae knows: the head gets the template's size, and the user is told; in millimetres
    nothing is said."""
    _, _, synthetic = scan_files
    for scale, said in ((0.8, True), (1.0, False)):
        scan, points = tmp_path / f"s{scale}.obj", tmp_path / f"s{scale}.json"
        trimesh.Trimesh(scale * synthetic.vertices, synthetic.faces, process=False).export(scan)
        points.write_text(json.dumps({n: list(map(float, scale * p)) for n, p in synthetic.landmarks.items()}))
        code = main(["adapt", str(scan), "--landmarks", str(points), "-o", str(tmp_path / f"h{scale}.glb"),
                     "--force", "--no-calibrate"])
        out = capsys.readouterr().out
        assert code == 0
        assert ("the scan's unit is none fae knows" in out and "the head has the template's size" in out) == said


def test_a_broken_template_is_named_before_the_fit(scan_files, capsys, tmp_path):
    """Case: `--template` a head with one skin vertex pulled 0.5 m out fitted for 17 s, then
    blamed the scan: "marble_bust.obj: the head is not whole (skin: 84 pairs of faces
    intersect)"."""
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel, write_facemodel

    scan, points, _ = scan_files
    head = read_facemodel(shipped_head_path())
    head.skin_vertices = head.skin_vertices.copy()
    head.skin_vertices[100, 1] += 0.5
    broken = tmp_path / "spike.glb"
    write_facemodel(head, broken)
    code, err = adapt(capsys, scan, "--landmarks", points, "--template", broken, "-o", tmp_path / "h.glb")
    assert code == 2 and f"template {broken}: not a whole head" in one_line(err) and "--force fits it" in err
    assert not (tmp_path / "h.glb").exists()
    # --force fits it all the same, saying why it should not
    code, err = adapt(capsys, scan, "--landmarks", points, "--template", broken, "-o", tmp_path / "h.glb", "--force")
    assert f"warning: template {broken}: not a whole head" in err
