"""FaceDefTables baked from the physics (`fae bake`) and the Player's "fdt" engine, on a
small calibrated head with a few FAPs baked."""

from __future__ import annotations

import argparse
import copy
import importlib

import numpy as np
import pytest

from fae.animate.bake import THRESHOLD, bake_tables, baked_model, has_baked_tables, settled_skin, table_borders
from fae.animate.calibrate import calibrate
from fae.animate.player import Player, playable_head
from fae.io.facemodel_gltf import read_facemodel, structural_problems, write_facemodel
from synthetic_head import synthetic_head

FAPS = (3, 5, 12, 19)  # open_jaw (skin carried by the mandible), a lip, a lip corner, an eyelid


def small_head():
    """The small synthetic head with every MPEG-4 feature point, so that it is a complete
    FaceModel file, calibrated."""
    return calibrate(synthetic_head(personalized=False, subdivisions=4, all_points=True, complete=False), passes=0)


@pytest.fixture(scope="module")
def physics():
    return Player(playable_head(small_head()))


@pytest.fixture(scope="module")
def baked(physics):
    return baked_model(physics.face, bake_tables(physics, FAPS))


@pytest.fixture(scope="module")
def fdt(baked):
    return Player(playable_head(baked, engine="fdt"))


def run_command(name: str, argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="fae")
    importlib.import_module(f"fae.commands.{name}").register(parser.add_subparsers())
    args = parser.parse_args([name, *argv])
    return args.func(args)


def one_fap(fap: int, value: float) -> np.ndarray:
    values = np.zeros(68)
    values[fap - 1] = value
    return values


def test_borders_split_each_sign_of_the_range_evenly():
    assert table_borders(12).tolist() == [-600.0, -400.0, -200.0, 0.0, 200.0, 400.0, 600.0]
    assert table_borders(3).tolist() == [0.0, 360.0, 720.0, 1080.0]  # open_jaw: unidirectional
    assert table_borders(12, 1).tolist() == [-600.0, 0.0, 600.0]


def test_baked_tables_are_marked_and_list_only_moving_vertices(baked):
    tables = {t.fap: t for t in baked.face_def_tables if t.source == "physics"}
    assert set(tables) == set(FAPS)
    assert has_baked_tables(baked)
    for t in tables.values():
        assert t.part == "skin" and 0 < len(t.vertices) < baked.skin_vertex_count
        assert t.displacements.shape == (len(t.borders) - 1, len(t.vertices), 3)
    assert structural_problems(baked) == []


@pytest.mark.parametrize("fap", FAPS)
def test_one_fap_at_a_border_plays_as_the_settled_physics(physics, fdt, fap):
    """At every border of its table a FAP alone moves the skin as the physics settles it,
    to within the vertices left out (each moving less than THRESHOLD)."""
    rest = physics.face.skin_vertices
    for b in table_borders(fap):
        if b == 0.0:
            continue
        settled = settled_skin(physics, one_fap(fap, b))
        fdt.reset()
        table = fdt.step(one_fap(fap, b))
        assert np.linalg.norm(table - settled, axis=1).max() <= THRESHOLD * 1.01
        assert np.linalg.norm(settled - rest, axis=1).max() > 5 * THRESHOLD  # it moved something


def test_between_borders_the_table_interpolates_the_physics(physics, fdt):
    """Half-way between two borders: the physics is smooth in the value, so the linear
    interpolation lands within a fifth of the motion there."""
    value = 0.5 * (table_borders(12)[4] + table_borders(12)[5])
    settled = settled_skin(physics, one_fap(12, value))
    fdt.reset()
    table = fdt.step(one_fap(12, value))
    motion = np.linalg.norm(settled - physics.face.skin_vertices, axis=1).max()
    assert np.linalg.norm(table - settled, axis=1).max() < 0.2 * motion


def test_the_fdt_engine_keeps_the_rigid_poses_and_the_head_rotation(physics, fdt):
    values = one_fap(3, 500.0)
    values[47] = 20000.0  # head pitch (AU)
    values[22] = 30000.0  # left eyeball yaw
    physics.reset()
    p_skin = physics.step(values)
    fdt.reset()
    f_skin = fdt.step(values)
    for bone in ("head", "jaw", "eye_l", "eye_r", "tongue"):
        assert np.allclose(fdt.bone_transforms[bone], physics.bone_transforms[bone], atol=1e-12)
    # the skin is carried by the head's pose in both (the jaw's skin lags in the physics' first frame)
    H = fdt.bone_transforms["head"]
    back = (f_skin - H[:3, 3]) @ H[:3, :3]
    assert np.abs(back - fdt.face.skin_vertices).max() < 0.05
    assert np.abs(np.mean(f_skin - p_skin, axis=0)).max() < 2e-3


def test_the_physics_engine_does_not_add_baked_tables(physics, baked):
    """A baked head simulates as the head it was baked from: its tables are the physics'
    own copy, not a motion of their own."""
    other = Player(playable_head(baked))
    values = one_fap(12, 300.0)
    values[64] = 400.0  # an ear: its derived table still applies
    physics.reset()
    for _ in range(5):
        a = physics.step(values)
        b = other.step(values)
    assert np.abs(a - b).max() < 1e-9


def test_a_baked_head_round_trips_through_the_glb(tmp_path, baked, fdt):
    path = tmp_path / "baked.glb"
    write_facemodel(baked, path)
    back = read_facemodel(path)
    mine = [t for t in baked.face_def_tables]
    theirs = [t for t in back.face_def_tables]
    assert [(t.fap, t.part, t.source) for t in theirs] == [(t.fap, t.part, t.source) for t in mine]
    for a, b in zip(mine, theirs):
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.borders, b.borders)
        assert np.array_equal(a.displacements, b.displacements)
    again = Player(playable_head(back, engine="fdt"))
    values = one_fap(5, 500.0)
    values[11] = -250.0
    fdt.reset()
    assert np.array_equal(again.step(values), fdt.step(values))


def test_a_table_with_an_unknown_source_is_refused(baked):
    odd = copy.deepcopy(baked)
    odd.face_def_tables[0].source = "guessed"
    assert any("source" in p for p in structural_problems(odd))


def test_the_fdt_engine_adds_fap_tables_together(fdt):
    """Superposition: two FAPs at once move the skin by the sum of each alone."""
    fdt.reset()
    rest = fdt.face.skin_vertices
    a = fdt.step(one_fap(5, 400.0)) - rest
    b = fdt.step(one_fap(12, -300.0)) - rest
    both = one_fap(5, 400.0)
    both[11] = -300.0
    assert np.abs(fdt.step(both) - rest - (a + b)).max() < 1e-12


def test_fdt_players_of_one_head_step_independently(fdt):
    a, b = Player(fdt.head), Player(fdt.head)
    sa = a.step(one_fap(12, 400.0))
    sb = b.step(one_fap(19, 500.0))
    assert np.abs(sa - a.step(one_fap(12, 400.0))).max() == 0.0
    assert np.abs(sa - sb).max() > 1e-4


def test_an_unknown_engine_is_refused(baked):
    with pytest.raises(ValueError, match="engine"):
        Player(playable_head(baked, engine="magic"))


def test_fae_bake_writes_a_baked_head_and_never_the_input(tmp_path, physics, capsys):
    head = tmp_path / "head.glb"
    write_facemodel(physics.face, head)
    before = head.read_bytes()
    out = tmp_path / "baked.glb"
    assert run_command("bake", [str(head), "-o", str(out), "--faps", "12", "--intervals", "1"]) == 0
    baked = read_facemodel(out)
    tables = [t for t in baked.face_def_tables if t.source == "physics"]
    assert [t.fap for t in tables] == [12] and tables[0].borders.tolist() == [-600.0, 0.0, 600.0]
    assert head.read_bytes() == before
    assert "1 FaceDefTables" in capsys.readouterr().err


@pytest.mark.parametrize("argv, expected", [
    (["{missing}", "-o", "{out}"], "not found"),
    (["{head}", "-o", "{out}", "--faps", "23"], "does not move the skin"),
    (["{head}", "-o", "{out}", "--faps", "x"], "--faps"),
    (["{head}", "-o", "{out}", "--faps", ""], "got ''"),  # an empty variable baked every FAP (45 s)
    (["{head}", "-o", "{head}"], "input head"),
    (["{head}", "-o", "{tmp}/out.txt"], "expected a .glb"),
    (["{head}", "-o", "{out}", "--intervals", "0"], "--intervals"),
])
def test_fae_bake_explains_bad_input_in_one_line(tmp_path, physics, capsys, argv, expected):
    head = tmp_path / "head.glb"
    write_facemodel(physics.face, head)
    names = {"missing": tmp_path / "none.glb", "out": tmp_path / "o.glb", "head": head, "tmp": tmp_path}
    assert run_command("bake", [a.format(**names) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert expected in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "o.glb").exists()


def test_a_head_baked_for_some_faps_knows_which_it_leaves_still(physics, fdt, tmp_path):
    """FAPs 3, 5, 12, 19 baked: the fdt engine has no table for the other skin FAPs (the ears'
    it derives); a FAP baked without a table (it moved nothing) counts as baked, through the
    head's .glb too; the physics engine leaves none still."""
    from fae.mpeg4.faptables import SKIN_TRANSLATION_FAPS

    missing = fdt.head.faps_without_tables
    assert set(missing) == set(SKIN_TRANSLATION_FAPS) - {3, 5, 12, 19, 65, 66, 67, 68}
    assert physics.head.faps_without_tables == []
    still = baked_model(physics.face, [t for t in fdt.tables if t.source == "physics"], faps=(3, 5, 12, 19, 4))
    assert 4 not in Player(playable_head(still, engine="fdt")).head.faps_without_tables
    path = tmp_path / "still.glb"
    write_facemodel(still, path)
    assert 4 not in Player(playable_head(read_facemodel(path), engine="fdt")).head.faps_without_tables


def test_faps_in_stream_counts_visemes_and_expressions_as_the_faps_they_move():
    """visemes.fap sends FAP 1 alone: the lips and jaw it moves are in use, no eyelid."""
    from fae.animate.highlevel import faps_in_stream
    from fae.io.fap import read_fap
    from test_play import REPO

    used = faps_in_stream(read_fap(REPO / "fap_streams" / "visemes.fap"))
    assert {3, 4, 5, 12, 13} <= used and not used & {1, 2, 19, 20}


@pytest.mark.slow
def test_fae_play_with_the_fdt_engine_writes_a_video(tmp_path, baked, capsys):
    """... and names the stream's FAPs the head was not baked for (the skin stays still for
    them): it played them without a word."""
    from test_play import short_stream

    head = tmp_path / "baked.glb"
    write_facemodel(baked, head)
    out = tmp_path / "fdt.mp4"
    assert run_command("play", [str(short_stream(tmp_path, frames=10)), "--head", str(head), "--engine", "fdt",
                                "-o", str(out), "--size", "160x120"]) == 0
    assert out.stat().st_size > 0
    notice = [line for line in capsys.readouterr().err.splitlines() if "no FaceDefTable" in line]
    assert len(notice) == 1 and "FAPs 4,6,7,10," in notice[0] and ",12," not in notice[0]


@pytest.mark.slow
def test_on_the_shipped_head_one_fap_at_its_borders_plays_as_the_physics(tmp_path):
    """The shipped head, FAPs 3 (the jaw's skin) and 12 (a lip corner) baked: at each border,
    FDT playback is the settled physics to within the vertices left out; the baked head
    round-trips through its .glb."""
    from fae.data import shipped_head_path

    physics = Player(playable_head(read_facemodel(shipped_head_path())))
    path = tmp_path / "baked.glb"
    write_facemodel(baked_model(physics.face, bake_tables(physics, (3, 12), intervals_per_side=2)), path)
    fdt = Player(playable_head(read_facemodel(path), engine="fdt"))
    assert sorted(t.fap for t in fdt.tables if t.source == "physics") == [3, 12]
    for fap in (3, 12):
        for b in table_borders(fap, 2):
            if b != 0.0:
                fdt.reset()
                error = np.linalg.norm(fdt.step(one_fap(fap, b)) - settled_skin(physics, one_fap(fap, b)), axis=1)
                assert error.max() <= THRESHOLD * 1.01, (fap, b)
