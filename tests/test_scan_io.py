"""Scan and landmark reading: every landmark format, and clear errors naming file and field."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fae.io.scan import IBUG68_TO_FDP, LandmarkError, indexed_vertices, read_landmarks, read_scan

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "heads"


def test_json_coordinates_and_vertex_indices(tmp_path):
    V = np.arange(30, dtype=float).reshape(10, 3)
    p = tmp_path / "lm.json"
    p.write_text(json.dumps({"9.3": [1, 2, 3], "3.7": 4, "08.3": [0, 0, 1]}))
    lm = read_landmarks(p, V)
    assert np.allclose(lm["9.3"], [1, 2, 3])
    assert np.allclose(lm["3.7"], V[4])
    assert "8.3" in lm  # names are normalized


@pytest.mark.parametrize("content, field", [
    ({"9.3": [1, 2]}, "9.3"),
    ({"nose": [1, 2, 3]}, "nose"),
    ({"3.7": 99}, "3.7"),
    ({"9.3": [1, 2, "abc"]}, "9.3"),  # numpy's "could not convert string to float" named neither
    ({"9.3": [1, 2, [3]]}, "9.3"),
])
def test_json_errors_name_the_field(tmp_path, content, field):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(content))
    with pytest.raises(LandmarkError, match=field) as exc:
        read_landmarks(p, np.zeros((10, 3)))
    assert "bad.json" in str(exc.value)


def test_invalid_json_names_the_line(tmp_path):
    p = tmp_path / "broken.json"
    p.write_text('{\n"9.3": [1, 2, 3],\n}')
    with pytest.raises(LandmarkError, match="line 3"):
        read_landmarks(p)


def test_csv_named_rows_and_ibug_rows(tmp_path):
    p = tmp_path / "named.csv"
    p.write_text("name,x,y,z\n9.3,1,2,3\n3.7,4,5,6\n")
    lm = read_landmarks(p)
    assert np.allclose(lm["3.7"], [4, 5, 6])
    pts = np.random.default_rng(0).normal(size=(68, 3))
    q = tmp_path / "ibug.csv"
    q.write_text("\n".join(",".join(f"{v:.9f}" for v in r) for r in pts))
    lm = read_landmarks(q)
    assert np.allclose(lm["9.3"], pts[30], atol=1e-8)  # nose tip
    assert np.allclose(lm["3.9"], pts[[46, 47]].mean(0), atol=1e-8)
    assert len(lm) == len(IBUG68_TO_FDP)
    bad = tmp_path / "short.csv"
    bad.write_text("1,2,3\n4,5,6\n")
    with pytest.raises(LandmarkError, match="68 iBUG"):
        read_landmarks(bad)


def test_scan_reading_merges_components_and_reports_bad_files(tmp_path):
    a = trimesh.creation.icosphere(2)
    b = trimesh.creation.icosphere(2)
    b.apply_translation([3, 0, 0])
    path = tmp_path / "two.ply"
    trimesh.util.concatenate([a, b]).export(path)
    V, F = read_scan(path)
    assert len(V) == 2 * len(a.vertices) and len(F) == 2 * len(a.faces)
    with pytest.raises(FileNotFoundError, match="missing.obj"):
        read_scan(tmp_path / "missing.obj")
    junk = tmp_path / "junk.stl"
    junk.write_bytes(b"not a mesh at all")
    with pytest.raises(ValueError, match="junk.stl"):
        read_scan(junk)
    # a .gltf whose buffer file is not beside it: "cannot read a mesh (gltf_buffer_0.bin)"
    gltf = tmp_path / "g" / "head.gltf"
    gltf.parent.mkdir()
    a.export(gltf)
    for buffer in gltf.parent.glob("*.bin"):
        buffer.unlink()
    with pytest.raises(ValueError, match=r"head.gltf: cannot read a mesh: it refers to \S+\.bin, which is not beside"):
        read_scan(gltf)


def test_menpo_ljson_every_version_gives_the_same_points(tmp_path):
    """menpo wrote three layouts over its versions; a file of any of them is the same 68 points
    (a version 2 file was read as MPEG-4 names: "'points' is not an MPEG-4 feature point")."""
    pts = np.random.default_rng(1).normal(size=(68, 3)).round(6).tolist()
    layouts = {
        "v3": {"version": 3, "groups": {"dlib": {"landmarks": {"points": pts, "connectivity": []},
                                                 "labels": [{"label": "all", "mask": list(range(68))}]}}},
        "v2": {"version": 2, "labels": [{"label": "all", "mask": list(range(68))}],
               "landmarks": {"points": pts, "connectivity": []}},
        "v1": {"version": 1, "groups": [{"label": "all", "connectivity": [],
                                         "landmarks": [{"point": p} for p in pts]}]},
        # as landmarker.io writes it: the 68 points as labelled parts, in iBUG order
        "v1 parts": {"version": 1, "groups": [{"label": label, "connectivity": [],
                                               "landmarks": [{"point": p} for p in pts[a:b]]}
                                              for label, a, b in (("chin", 0, 17), ("leye", 17, 22), ("reye", 22, 27),
                                                                  ("nose", 27, 36), ("leye", 36, 42), ("reye", 42, 48),
                                                                  ("mouth", 48, 68))]},
    }
    read = {}
    for name, data in layouts.items():
        path = tmp_path / f"{name}.ljson"
        path.write_text(json.dumps(data))
        read[name] = read_landmarks(path)
    assert np.allclose(read["v3"]["9.3"], pts[30])
    for name in ("v2", "v1", "v1 parts"):
        assert read[name].keys() == read["v3"].keys()
        assert all(np.allclose(read[name][k], read["v3"][k]) for k in read["v3"])
    short = tmp_path / "short.ljson"
    short.write_text(json.dumps({"version": 2, "landmarks": {"points": pts[:67]}}))
    with pytest.raises(LandmarkError, match="expected 68 iBUG points"):
        read_landmarks(short)


def test_menpo_ljson_gives_mirror_consistent_fdps():
    path = SHARED / "menpo3d_template" / "template.ljson"
    if not path.exists():
        pytest.skip("shared data not present")
    lm = read_landmarks(path)
    # the face's own left (+x) holds the left-eye and left mouth-corner points
    assert lm["3.7"][0] > lm["3.11"][0] > lm["3.8"][0] > lm["3.12"][0]
    assert lm["8.3"][0] > lm["8.4"][0]
    assert lm["9.3"][1] > lm["8.1"][1] > lm["2.1"][1]


def _textured_obj(path) -> np.ndarray:
    """An OBJ as photogrammetry tools write it: one texture coordinate per face corner (so
    every vertex is split along seams when read as a mesh) and an unused first vertex.
    Returns the file's own vertices (its `v` lines, in order)."""
    sphere = trimesh.creation.icosphere(1)
    V = np.vstack([[[9.0, 9.0, 9.0]], sphere.vertices])  # vertex 0: in the file, in no face
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
    for k, (a, b, c) in enumerate(sphere.faces):
        lines += [f"vt {0.01 * k:.4f} 0.1", f"vt {0.01 * k:.4f} 0.2", f"vt {0.01 * k:.4f} 0.3"]
        lines.append(f"f {a + 2}/{3 * k + 1} {b + 2}/{3 * k + 2} {c + 2}/{3 * k + 3}")
    path.write_text("\n".join(lines) + "\n")
    return V


def test_vertex_indices_count_the_scan_files_own_vertices(tmp_path):
    """`{"9.3": 5}` is the file's sixth `v` line, however the mesh reader splits the
    vertices along texture seams or drops unused ones (it pointed elsewhere: a textured
    OBJ's landmarks bent the fit)."""
    obj = tmp_path / "textured.obj"
    V_file = _textured_obj(obj)
    V, F = read_scan(obj)
    assert len(V) != len(V_file)  # the reader's vertices are not the file's
    lm = tmp_path / "lm.json"
    lm.write_text(json.dumps({"9.3": 5, "2.1": 0}))
    got = read_landmarks(lm, lambda: indexed_vertices(obj, V))
    assert np.allclose(got["9.3"], V_file[5]) and np.allclose(got["2.1"], V_file[0])
    calls = []
    read_landmarks(tmp_path / "lm.json", lambda: calls.append(1) or V_file)
    assert calls == [1]  # the scan is read again once, and only for indices
    coords = tmp_path / "xyz.json"
    coords.write_text(json.dumps({"9.3": [1, 2, 3]}))
    read_landmarks(coords, lambda: calls.append(1) or V_file)
    assert calls == [1]


def test_a_face_naming_a_missing_vertex_is_refused_by_the_reader(tmp_path):
    """(`fae play --head` crashed on it with a traceback; `fae adapt` alone checked.)"""
    path = tmp_path / "holey.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 6\n")
    with pytest.raises(ValueError, match=r"holey.ply: a face names vertex 6; the file has 3"):
        read_scan(path)


@pytest.mark.parametrize("name, text, expected", [
    ("bom.csv", "\ufeff9.3,1,2,3\n3.7,4,5,6\n", None),
    ("label.csv", "label,x,y,z\n9.3,1,2,3\n", None),  # any header naming x, y, z (only name/fdp/point were)
    ("id.csv", "id,X,Y,Z\n9.3,1,2,3\n", None),
    ("bom.json", "\ufeff" + json.dumps({"9.3": [1, 2, 3]}), None),
    ("comments.csv", "# my points\n\n# more\n9.3,1,2,x\n", r"comments.csv: line 4: x, y, z must be numbers"),
    ("dup.csv", "9.3,1,2,3\n3.7,4,5,6\n9.3,7,8,9\n", r"dup.csv: line 3: feature point 9.3 is given twice \(first on line 1\)"),
    ("dup.json", '{"9.3": [1, 2, 3], "9.3": [4, 5, 6]}', r"dup.json: field '9.3' is given twice"),
    ("zero.json", '{"9.3": [1, 2, 3], "09.3": [4, 5, 6]}', r"zero.json: feature point 9.3 is given twice"),
    ("bogus.csv", "9.3,1,2,3\n9.99,4,5,6\n", r"bogus.csv: line 2: '9.99' is not one of the standard's 84"),
    ("groups.ljson", json.dumps({"groups": [{"label": "face", "landmarks": {"points": [[0, 0]]}}]}), r"groups.ljson: ljson"),
    ("huge.json", '{"9.3": [1' + "0" * 400 + ', 2, 3]}', r"huge.json"),
])
def test_landmark_files_as_people_write_them(tmp_path, name, text, expected):
    """A byte-order mark (spreadsheets, Windows editors) is read; a bad line is named by its
    line in the file; a point given twice, a name the standard does not have and a
    malformed ljson are refused, naming the file: never a traceback, never the last value."""
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    if expected is None:
        assert np.allclose(read_landmarks(path)["9.3"], [1, 2, 3])
    else:
        with pytest.raises(LandmarkError, match=expected):
            read_landmarks(path)


def test_ibug_files_with_a_header_or_several_groups(tmp_path):
    pts = np.random.default_rng(1).normal(size=(68, 3))
    csv_path = tmp_path / "ibug.csv"
    csv_path.write_text("x,y,z\n" + "\n".join(",".join(f"{v:.9f}" for v in r) for r in pts))
    assert np.allclose(read_landmarks(csv_path)["9.3"], pts[30], atol=1e-8)
    ljson = tmp_path / "two.ljson"
    ljson.write_text(json.dumps({"groups": {"brows": {"landmarks": {"points": [[0, 0, 0]] * 10}},
                                            "face": {"landmarks": {"points": pts.tolist()}}}}))
    assert np.allclose(read_landmarks(ljson)["9.3"], pts[30])  # the 68-point group, not the first


def test_vertex_indices_of_an_obj_with_several_materials(tmp_path):
    """A reader joins an OBJ's materials as pieces: their vertices in another order, some
    repeated. An index still names the file's own `v` line."""
    obj = tmp_path / "two_materials.obj"
    V_file = np.arange(30, dtype=float).reshape(10, 3)
    lines = [f"v {x:g} {y:g} {z:g}" for x, y, z in V_file] + ["vt 0 0", "vt 1 0", "vt 0 1"]
    lines += ["usemtl a", "f 1/1 2/2 3/3", "f 8/1 9/2 10/3", "usemtl b", "f 3/1 4/2 8/3", "f 5/1 6/2 7/3"]
    obj.write_text("\n".join(lines) + "\n")
    V, _ = read_scan(obj)
    lm = tmp_path / "lm.json"
    lm.write_text(json.dumps({"9.3": 7}))
    assert np.allclose(read_landmarks(lm, lambda: indexed_vertices(obj, V))["9.3"], V_file[7])
    lm.write_text(json.dumps({"9.3": 12}))
    with pytest.raises(LandmarkError, match="outside 0..9"):
        read_landmarks(lm, lambda: indexed_vertices(obj, V))


def test_an_obj_with_relative_indices_tabs_and_crlf_reads_as_written(tmp_path):
    """The OBJ format lets a face count back from the vertices read so far (f -3 -2 -1) and
    fields be split by tabs; exporters do both, and Windows tools end lines with CRLF. The
    mesh reader took the relative indices as the wrong vertices, silently, and a file with
    tabs as one without triangles. Read now as the same file written plainly, texture too."""
    from PIL import Image

    from fae.animate.retarget import _read_surface

    plain = tmp_path / "plain.obj"
    V_file = _textured_obj(plain)
    Image.new("RGB", (4, 4), (200, 120, 90)).save(tmp_path / "skin.png")
    (tmp_path / "skin.mtl").write_text("newmtl skin\nmap_Kd skin.png\n")
    lines = plain.read_text().splitlines()
    faces = [line for line in lines if line.startswith("f ")]
    kept = [line for line in lines if not line.startswith(("f ", "vt "))]
    written = ["mtllib\tskin.mtl", "usemtl\tskin"] + [line.replace(" ", "\t") for line in kept]
    for k, face in enumerate(faces):
        written += [f"vt\t{0.01 * k:.4f} 0.1", f"vt {0.01 * k:.4f}\t0.2", f"vt {0.01 * k:.4f} 0.3"]
        corners = [int(c.split("/")[0]) - len(V_file) - 1 for c in face.split()[1:]]  # from the last v line
        written.append("f\t" + " ".join(f"{v}/{t}" for v, t in zip(corners, (-3, -2, -1))))
    relative = tmp_path / "relative.obj"
    relative.write_bytes(("\r\n".join(written) + "\r\n").encode())
    plain.write_text("mtllib skin.mtl\nusemtl skin\n" + plain.read_text())

    V0, F0 = read_scan(plain)
    V1, F1 = read_scan(relative)
    assert np.allclose(V1, V0) and np.array_equal(F1, F0)
    assert np.allclose(indexed_vertices(relative, V1), V_file)  # the file's own `v` lines, tabs or not
    uv0, texture0 = _read_surface(str(plain), len(V0))
    uv1, texture1 = _read_surface(str(relative), len(V1))
    assert uv1 is not None and np.allclose(uv1, uv0)
    assert texture1 is not None and np.array_equal(texture1, texture0)
    # and the file itself is read, not changed
    assert relative.read_bytes().count(b"\t") > len(V_file)
    # relative indices alone (spaces only), a byte-order mark, an indented face, a comment
    # after one: each was read as the wrong vertices or as no triangles
    square = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
    for name, text in (("minus", square + "f -4 -3 -2\nf -4 -2 -1\n"),
                       ("bom", "\ufeff" + square + "f -4 -3 -2\nf -4 -2 -1\n"),
                       ("indented", square + "  f 1 2 3\n  f 1 3 4\n"),
                       ("comment", square + "f 1 2 3 # first\nf 1 3 4  # second\n")):
        (tmp_path / f"{name}.obj").write_bytes(text.encode())
        V, F = read_scan(tmp_path / f"{name}.obj")
        assert np.allclose(V, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]) and np.array_equal(F, [[0, 1, 2], [0, 2, 3]])
        assert np.allclose(indexed_vertices(tmp_path / f"{name}.obj", V), V)
    # an index counting back past the first vertex names the line
    (tmp_path / "past.obj").write_text(square + "f 1 2 3\nf -5 -4 -3\n")
    with pytest.raises(ValueError, match=r"past.obj: cannot read a mesh \(line 6: index -5 counts back past the 4"):
        read_scan(tmp_path / "past.obj")
