"""Heads whose file reads but whose data the engine cannot use as it stands: every command
that animates one says so in one line (exit 2) or copes, never a traceback or a hang."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fae.cli import main
from fae.commands.common import load_head
from fae.io.facemodel_gltf import write_facemodel

STREAM = "fap_streams/visemes.fap"


@pytest.fixture(scope="module")
def shipped():
    return load_head(None)[0]


@pytest.mark.parametrize("params, field", [
    ({"active_rings": 1_000_000_000}, "active_rings"),  # grew a mask a billion times: a hang
    ({"kappa_epidermis": 1e300}, "kappa_epidermis"),  # substeps without end: a hang
    ({"drag": "fast"}, "drag"),  # a traceback
    ({"layer_depth_fractions": [0.0, 1.0, 0.5]}, "layer_depth_fractions"),  # a traceback
    ({"cfl": 1e-9}, "cfl"),  # a billion times the substeps: a frame took minutes, `template check` said valid
    ({"density": 1e-9}, "density"),  # the same through the particles' mass
    ({"drag_carried_skin": 1.5}, "drag_carried_skin"),  # skin pushed ahead of its moving hold
])
def test_layer_params_the_simulation_cannot_use_are_named(shipped, tmp_path, capsys, params, field):
    path = tmp_path / "head.glb"
    write_facemodel(dataclasses.replace(shipped, layer_params={**shipped.layer_params, **params}), path)
    assert main(["template", "check", str(path)]) == 1
    assert f"problem: layer_params.{field}: expected" in capsys.readouterr().out
    assert main(["play", STREAM, "--head", str(path), "-o", str(tmp_path / "x.mp4"), "--size", "64x48"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fae play: {path}: cannot animate it: layer_params.{field}: expected") and err.count("\n") == 1
    assert not (tmp_path / "x.mp4").exists()


def test_a_head_without_eyeballs_plays(shipped, tmp_path, capsys):
    """`template check` passed such a head and every animating command then stopped on
    KeyError 'eye_l'. Without eyes the gaze FAPs move nothing and the rest plays."""
    points = dict(shipped.feature_points)
    points["3.5"], points["3.6"] = points["3.1"], points["3.2"]  # the pupils on the lids (the eye separation)
    assert not any(p.part.startswith("eye") for p in points.values())
    eyeless = dataclasses.replace(shipped, parts={k: v for k, v in shipped.parts.items() if not k.startswith("eye")},
                                  eye_centers={}, feature_points=points)
    path = tmp_path / "eyeless.glb"
    write_facemodel(eyeless, path)
    gaze = tmp_path / "gaze.fap"
    mask = ["0"] * 68
    mask[22] = mask[24] = "1"  # yaw and pitch of the left eyeball
    gaze.write_text("2.1 gaze 25 2\n" + "".join(f"{' '.join(mask)}\n{i} 20000 10000\n" for i in range(2)))
    assert main(["play", str(gaze), "--head", str(path), "-o", str(tmp_path / "x.mp4"), "--size", "64x48"]) == 0, \
        capsys.readouterr().err
    assert (tmp_path / "x.mp4").stat().st_size > 0


def test_a_mapping_of_the_wrong_shape_is_one_to_recalibrate(shipped):
    from fae.animate.controls import FapControls, MappingMismatch

    for bad in ({"layout": [27, 4]}, {"layout": "many"}, {"field_faps": [["x"]]}, {"gain_pos": "high"}):
        with pytest.raises(MappingMismatch, match="fap_mapping"):
            FapControls(dataclasses.replace(shipped, fap_mapping={**shipped.fap_mapping, **bad}))


def test_growing_a_mask_stops_when_nothing_more_is_reached():
    import scipy.sparse as sp

    from fae.sim.build import dilate

    A = sp.csr_matrix(np.array([[0, 1, 0], [1, 0, 0], [0, 0, 0]], dtype=float))
    assert dilate(np.array([True, False, False]), A, 10**12).tolist() == [True, True, False]


def test_a_folder_given_as_a_head_is_named_as_one(tmp_path, capsys):
    assert main(["render", str(tmp_path), "-o", str(tmp_path / "x.png")]) == 2
    assert "a folder; expected a head file" in capsys.readouterr().err


def test_counts_written_as_json_floats_are_whole_numbers(shipped):
    """json.dumps writes 3.0 for a float 3: such a head built before and must still."""
    from fae.sim.build import DEFAULTS, checked_params

    assert checked_params({**DEFAULTS, "active_rings": 3.0, "fold_passes": 0.0})["active_rings"] == 3.0
    for bad in (2.5, float("nan"), True, "3"):
        with pytest.raises(ValueError, match="active_rings"):
            checked_params({**DEFAULTS, "active_rings": bad})


def test_coordinates_no_head_has_are_refused_on_reading(shipped, tmp_path, capsys):
    """Skin coordinates of 1e160 (finite) read, and the renderer failed on a singular
    matrix with a traceback; a million times the head's size is refused as well."""
    path = tmp_path / "huge.glb"
    write_facemodel(dataclasses.replace(shipped, skin_vertices=shipped.skin_vertices * 1e6), path, check=False)
    assert main(["render", str(path), "-o", str(tmp_path / "x.png")]) == 2
    assert "skin_vertices: expected metres" in capsys.readouterr().err


def test_a_negative_buffer_offset_is_named(tmp_path, capsys):
    """The reader said "malformed FaceModel file (ValueError: offset must be non-negative...)"."""
    import json
    import struct

    from fae.data import shipped_head_path

    data = shipped_head_path().read_bytes()
    (length,) = struct.unpack_from("<I", data, 12)  # the JSON chunk's, after the 12-byte header
    doc = json.loads(data[20:20 + length])
    doc["bufferViews"][-1]["byteOffset"] = -8
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    rest = data[20 + length:]  # the BIN chunk, as it was
    path = tmp_path / "negative.glb"
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(text) + len(rest))
                     + struct.pack("<I4s", len(text), b"JSON") + text + rest)
    assert main(["render", str(path), "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert f"bufferViews[{len(doc['bufferViews']) - 1}].byteOffset: expected a byte offset >= 0, got -8" in err
