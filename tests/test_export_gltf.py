"""`fae export`: the head as a plain glTF scene with morph targets and a stream's animation,
checked with the Khronos validator and against the Player's FDT engine."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from fae.animate.bake import bake_tables, baked_model
from fae.animate.morphs import MorphWeights, displacement, morph_targets
from fae.animate.player import Player, playable_head
from fae.io.facemodel_gltf import write_facemodel
from test_bake import FAPS, small_head
from test_facemodel_gltf import validate

REPO = Path(__file__).resolve().parent.parent
FPS = 20.0


def run_command(name: str, argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="fae")
    importlib.import_module(f"fae.commands.{name}").register(parser.add_subparsers())
    args = parser.parse_args([name, *argv])
    return args.func(args)


def moving_stream(path: Path, frames: int = 30) -> Path:
    """A stream at FPS moving the baked FAPs, an eye, the head, and the tongue (roll: a scale)."""
    from fae.io.fap import FapFrame, FapHeader, write_fap

    out = []
    for i in range(frames):
        s = np.sin(2 * np.pi * i / frames)
        values = np.zeros(68)
        values[[2, 4, 11, 18]] = [900 * abs(s), 700 * s, -500 * s, 400 * abs(s)]   # 3, 5, 12, 19
        values[[22, 47, 43, 46]] = [30000 * s, 15000 * s, 300 * abs(s), 40000 * abs(s)]  # 23, 48, 44, 47
        mask = values != 0.0
        out.append(FapFrame(number=i, mask=mask, values=values))
    write_fap(path, FapHeader("2.1", path.stem, FPS, len(out)), out)
    return path


@pytest.fixture(scope="module")
def baked_file(tmp_path_factory):
    physics = Player(playable_head(small_head()))
    path = tmp_path_factory.mktemp("export") / "baked.glb"
    write_facemodel(baked_model(physics.face, bake_tables(physics, FAPS)), path)
    return path


@pytest.fixture(scope="module")
def exported(baked_file):
    stream = moving_stream(baked_file.parent / "moving.fap")
    out = baked_file.parent / "scene.glb"
    assert run_command("export", [str(baked_file), str(stream), "-o", str(out)]) == 0
    return out, stream


def accessor_values(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """(count, n) float values of a FLOAT accessor, sparse ones included."""
    acc = gltf.accessors[index]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc.type]
    out = np.zeros((acc.count, width), dtype=np.float32)
    if acc.bufferView is not None:
        view = gltf.bufferViews[acc.bufferView]
        start = view.byteOffset + (acc.byteOffset or 0)
        out[:] = np.frombuffer(blob, np.float32, acc.count * width, start).reshape(acc.count, width)
    if acc.sparse is not None:
        s = acc.sparse
        idx_view = gltf.bufferViews[s.indices.bufferView]
        idx = np.frombuffer(blob, np.uint32, s.count, idx_view.byteOffset)
        val_view = gltf.bufferViews[s.values.bufferView]
        out[idx] = np.frombuffer(blob, np.float32, s.count * width, val_view.byteOffset).reshape(s.count, width)
    return out


def played_scene(path: Path) -> tuple[dict, np.ndarray, dict, np.ndarray, np.ndarray, np.ndarray]:
    """What a scene's animation holds: (node name -> index, key times (N,), (node, path) ->
    key values, the skin's rest (V, 3), its morph targets (T, V, 3), weights (N, T))."""
    gltf = pygltflib.GLTF2.load(str(path))
    blob = gltf.binary_blob()
    nodes = {n.name: i for i, n in enumerate(gltf.nodes)}
    anim = gltf.animations[0]
    keys = {}
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        times = accessor_values(gltf, blob, sampler.input)[:, 0]
        keys[(ch.target.node, ch.target.path)] = accessor_values(gltf, blob, sampler.output)
    prim = gltf.meshes[gltf.nodes[nodes["skin"]].mesh].primitives[0]
    rest = accessor_values(gltf, blob, prim.attributes.POSITION)
    targets = np.stack([accessor_values(gltf, blob, t["POSITION"]) for t in prim.targets])  # (T, V, 3)
    weights = keys[(nodes["skin"], "weights")].reshape(len(times), len(targets))
    return nodes, times, keys, rest, targets, weights


def node_matrix(node) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    M = np.eye(4)
    R = Rotation.from_quat(node.rotation).as_matrix() if node.rotation else np.eye(3)
    M[:3, :3] = R * np.asarray(node.scale if node.scale else [1, 1, 1])[None, :]
    M[:3, 3] = node.translation if node.translation else 0.0
    return M


def test_morph_targets_reproduce_the_tables_exactly(baked_file):
    from fae.io.facemodel_gltf import read_facemodel

    player = Player(playable_head(read_facemodel(baked_file), engine="fdt"))
    targets = morph_targets(player.tables)
    mw = MorphWeights(targets)
    rng = np.random.default_rng(1)
    for _ in range(5):
        values = np.zeros(68)
        values[[f - 1 for f in FAPS]] = rng.uniform(-800, 1000, len(FAPS))
        values = player.frame_values(values)
        w = mw.weights(values)
        assert np.all((w >= 0) & (w <= 1))
        player.reset()
        skin = player.step(values)
        assert np.abs(player.face.skin_vertices + displacement(targets, w, len(skin)) - skin).max() < 1e-12


def test_the_exported_scene_passes_the_khronos_validator(exported):
    report = validate(exported[0])
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    info = report["info"]
    assert info["animationCount"] == 1 and info["hasMorphTargets"]


def test_the_scene_has_the_meshes_bones_and_named_targets(exported):
    gltf = pygltflib.GLTF2.load(str(exported[0]))
    names = [n.name for n in gltf.nodes]
    for name in ("head_bone", "jaw_bone", "eye_l_bone", "eye_r_bone", "tongue_bone", "skin", "eye_l", "eye_r",
                 "upper_teeth", "lower_teeth", "tongue"):
        assert name in names
    assert "cranium" not in names and "mandible" not in names
    skin = gltf.meshes[[m.name for m in gltf.meshes].index("skin")]
    target_names = skin.extras["targetNames"]
    assert len(target_names) == len(skin.primitives[0].targets) == len(skin.weights) > 0
    assert "raise_l_cornerlip 0..200" in target_names and "open_jaw 720..1080" in target_names
    assert skin.primitives[0].attributes.COLOR_0 is not None


def test_the_animation_matches_the_players_fdt_output(exported, baked_file):
    """At a few frames, the animation's morph weights and node poses, sampled at the frame's
    time, give the skin and bones the Player's FDT engine gives (float32 in the file)."""
    from fae.io.facemodel_gltf import read_facemodel
    from fae.io.fap import read_fap
    from fae.io.frames import dense_frames

    path, stream = exported
    gltf = pygltflib.GLTF2.load(str(path))
    nodes, times, keys, rest, targets, weights = played_scene(path)
    assert np.allclose(times, np.arange(len(times)) / FPS)

    player = Player(playable_head(read_facemodel(baked_file), engine="fdt"))
    played = list(player.play(dense_frames(read_fap(stream))))
    assert len(played) == len(times)
    parents = {"head": None, "eye_l": "head", "eye_r": "head", "jaw": "head", "tongue": "jaw"}
    for i in (0, 7, 15, 22, len(times) - 1):
        world = {}
        for bone, parent in parents.items():
            n = gltf.nodes[nodes[f"{bone}_bone"]]
            local = pygltflib.Node(translation=keys[(nodes[f"{bone}_bone"], "translation")][i].tolist(),
                                   rotation=keys[(nodes[f"{bone}_bone"], "rotation")][i].tolist(),
                                   scale=(keys[(nodes[f"{bone}_bone"], "scale")][i].tolist()
                                          if (nodes[f"{bone}_bone"], "scale") in keys else n.scale))
            world[bone] = node_matrix(local) if parent is None else world[parent] @ node_matrix(local)
            assert np.abs(world[bone] - played[i].bone_transforms[bone]).max() < 1e-5, (bone, i)
        skin = rest + np.tensordot(weights[i], targets, axes=1)
        H = world["head"]
        skin = skin @ H[:3, :3].T + H[:3, 3]
        assert np.abs(skin - played[i].skin_vertices).max() < 2e-5, i
    assert np.abs(weights).max() > 0.5  # the stream does move the face


def test_without_a_stream_the_scene_has_no_animation(baked_file, tmp_path):
    out = tmp_path / "still.glb"
    assert run_command("export", [str(baked_file), "-o", str(out)]) == 0
    gltf = pygltflib.GLTF2.load(str(out))
    assert not gltf.animations
    assert validate(out)["issues"]["numErrors"] == 0


@pytest.mark.parametrize("argv, expected", [
    (["{missing}", "-o", "{out}"], "not found"),
    (["{head}", "{bad}", "-o", "{out}"], "bad.fap"),
    (["{head}", "-o", "{head}"], "input file"),
    (["{head}", "-o", "{tmp}/scene.gltf"], "expected a .glb"),
    (["{head}", "{bad}", "-o", "{out}", "--fps", "0"], "--fps"),
    (["{head}", "{empty}", "-o", "{out}"], "empty.fap: no frames to animate"),  # was: a scene without animation, exit 0
    # two frames 25 million apart, held as long as they ask: refused before a frame is played
    # (it ran for minutes and past a gigabyte)
    (["{head}", "{gap}", "-o", "{out}", "--max-hold", "1e6"], "gap.fap: 25000001 frames at 25 fps would hold"),
])
def test_fae_export_explains_bad_input_in_one_line(tmp_path, baked_file, capsys, argv, expected):
    bad = tmp_path / "bad.fap"
    bad.write_text("not a fap file\n")
    empty = tmp_path / "empty.fap"
    empty.write_text("2.1 empty 25 0\n")
    mask = " ".join("1" if k == 18 else "0" for k in range(68))
    gap = tmp_path / "gap.fap"
    gap.write_text(f"2.1 gap 25 2\n{mask}\n0 100\n{mask}\n25000000 200\n")
    names = {"missing": tmp_path / "none.glb", "out": tmp_path / "o.glb", "head": baked_file, "tmp": tmp_path,
             "bad": bad, "empty": empty, "gap": gap}
    before = baked_file.read_bytes()
    assert run_command("export", [a.format(**names) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert expected in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "o.glb").exists()
    assert baked_file.read_bytes() == before


@pytest.mark.slow
def test_the_shipped_head_exports_expressions_for_the_validator(tmp_path, capsys):
    """The shipped head, a few FAPs baked, with fap_streams/expressions.fap: 0 validator errors."""
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel

    face = read_facemodel(shipped_head_path())
    physics = Player(playable_head(face))
    head = tmp_path / "baked.glb"
    write_facemodel(baked_model(physics.face, bake_tables(physics, (3, 12, 13, 31, 32), intervals_per_side=2)), head)
    out = tmp_path / "expressions.glb"
    assert run_command("export", [str(head), str(REPO / "fap_streams" / "expressions.fap"), "-o", str(out)]) == 0
    report = validate(out)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    assert report["info"]["animationCount"] == 1
    # the brows and lids the expressions move were not baked: said, not left to be found in the scene
    notice = [line for line in capsys.readouterr().err.splitlines() if "no FaceDefTable" in line]
    assert len(notice) == 1 and ",19,20," in notice[0] and ",31," not in notice[0]


def test_a_played_meshs_frames_become_the_fewest_shapes_that_rebuild_them():
    """shape_targets: frames made of five shapes come back as five targets that rebuild every
    frame (float32 offsets, as `fae play -o OUT.glb` holds them); still frames need none; with
    too few targets allowed, the error it reports is the rebuild's real worst."""
    from fae.animate.morphs import shape_targets

    rng = np.random.default_rng(3)
    shapes = rng.normal(scale=2e-3, size=(5, 3000, 3))
    frames = np.einsum("nk,kvd->nvd", rng.normal(size=(60, 5)), shapes).astype(np.float32)
    frames[7] = 0.0  # a frame at rest
    targets, weights, error = shape_targets(frames)
    assert len(targets) == 5 and weights.shape == (60, 5) and error <= 1e-4
    rebuilt = np.stack([displacement(targets, w, 3000) for w in weights])
    assert np.abs(rebuilt - frames).max() < 1e-5 and np.abs(weights[7]).max() < 1e-9
    assert shape_targets(np.zeros((4, 3000, 3), np.float32))[0] == []
    few, w3, worst = shape_targets(frames, max_targets=3)
    rebuilt = np.stack([displacement(few, w, 3000) for w in w3])
    assert len(few) == 3 and worst > 1e-4
    assert abs(np.sqrt(np.max(np.sum((rebuilt - frames) ** 2, axis=2))) - worst) < 1e-6
