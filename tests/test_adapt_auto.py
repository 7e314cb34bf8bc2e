"""Feature points found on a scan without landmarks (paper 003), and `fae adapt` without
--landmarks, on synthetic people with known feature points and on a shared face mesh."""

from pathlib import Path

import numpy as np
import pytest

from fae.adapt.auto_landmarks import CylindricalError, auto_landmarks, ga_refine
from fae.adapt.query import MeshQuery
from fae.anatomy.checks import facemodel_problems
from fae.data import shipped_head_path
from fae.io.facemodel_gltf import read_facemodel

from test_adapt_transfer import person_scan

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "heads"


@pytest.fixture(scope="module")
def template():
    return read_facemodel(shipped_head_path())


@pytest.fixture(scope="module")
def found(template):
    scan = person_scan(template, seed=5, max_angle=1.0)  # turned by up to 57 degrees, millimetres
    landmarks, report = auto_landmarks(template, scan.vertices, scan.faces)
    return scan, landmarks, report


def test_feature_points_are_found_on_a_turned_millimetre_scan(found):
    scan, landmarks, report = found
    assert report["scan_unit"] == "mm"
    assert "9.3" in report["detected"]
    assert len(landmarks) >= 40
    err = np.array([np.linalg.norm(landmarks[n] - scan.landmarks[n]) for n in landmarks])  # mm
    assert np.linalg.norm(landmarks["9.3"] - scan.landmarks["9.3"]) < 6.0
    assert np.median(err) < 10.0 and err.max() < 30.0, err


def test_a_head_adapted_from_found_points_is_valid(found, template):
    from fae.adapt.transfer import adapt_facemodel

    scan, landmarks, _ = found
    model, report = adapt_facemodel(template, scan.vertices, scan.faces, landmarks)
    assert facemodel_problems(model) == []
    assert report["final"]["scan_to_model_rms"] < 3e-3


def test_the_genetic_search_never_loses_its_best_and_stays_on_the_surface(template):
    rng = np.random.default_rng(0)
    V, F = template.skin_vertices, template.skin_faces
    q = MeshQuery(V, F)
    fdp = template.feature_point_positions()
    names = ["9.3", "8.1", "8.2", "8.3", "8.4", "3.7", "3.8", "3.11", "3.12", "2.1", "11.1"]
    PL = np.array([fdp[n] for n in names])
    Q0 = q.closest_points(PL + rng.normal(scale=0.003, size=PL.shape))[0]  # disturbed points
    front = np.flatnonzero(V[:, 2] > 0.05)[::20]
    error = CylindricalError(V[front], q, 0.5 * (V.min(0) + V.max(0)))
    best, history = ga_refine(PL, Q0, np.array([n == "9.3" for n in names]), error,
                              lambda X: q.closest_points(X)[0], population=10, generations=6)
    assert all(b <= a + 1e-15 for a, b in zip(history, history[1:]))  # elitism
    assert history[-1] < history[0]
    assert np.allclose(best[0], Q0[0])  # the detected nose tip stays
    assert np.max(q.closest_points(best)[1]) < 1e-6


@pytest.mark.slow
def test_fae_adapt_without_landmarks_on_a_shared_face(tmp_path, capsys):
    obj = SHARED / "meshmonk_template" / "Template.obj"
    if not obj.exists():
        pytest.skip("shared data not present")
    import json

    from fae.cli import main

    out, rep = tmp_path / "face.glb", tmp_path / "face.json"
    assert main(["adapt", str(obj), "--method", "multilevel", "-o", str(out), "--report", str(rep),
                 "--no-calibrate"]) == 0
    assert "found automatically" in capsys.readouterr().err
    report = json.loads(rep.read_text())
    assert report["automatic_feature_points"]["scan_unit"] == "mm"
    assert report["final"]["scan_to_model_rms"] < 5e-3
    model = read_facemodel(out)
    assert len(model.feature_points) == 84
