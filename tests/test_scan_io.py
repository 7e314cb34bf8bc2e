"""Scan and landmark reading: every landmark format, and clear errors naming file and field."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fae.io.scan import IBUG68_TO_FDP, LandmarkError, read_landmarks, read_scan

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


def test_menpo_ljson_gives_mirror_consistent_fdps():
    path = SHARED / "menpo3d_template" / "template.ljson"
    if not path.exists():
        pytest.skip("shared data not present")
    lm = read_landmarks(path)
    # the face's own left (+x) holds the left-eye and left mouth-corner points
    assert lm["3.7"][0] > lm["3.11"][0] > lm["3.8"][0] > lm["3.12"][0]
    assert lm["8.3"][0] > lm["8.4"][0]
    assert lm["9.3"][1] > lm["8.1"][1] > lm["2.1"][1]
