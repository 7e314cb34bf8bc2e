"""`fae inspect`: summary of a .fap stream, exit 0 when understood, 2 when rejected."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fae.cli import main


def test_json_summary_of_a_real_file(shared_data, capsys):
    path = shared_data / "fap" / "xface_test.fap"
    assert main(["inspect", str(path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["version"] == "2.1" and summary["fps"] == 25.0
    assert summary["frame_count"] == summary["declared_frame_count"] == 43
    assert summary["faps_used"][:3] == [3, 4, 5] and 48 in summary["faps_used"] and 1 not in summary["faps_used"]
    assert summary["faps_used"] == sorted(summary["faps_used"])
    # (Xface's encoder sends the unidirectional cheek lifts slightly negative, -7: played as
    # 0, and not news, as the player has it)
    assert summary["warnings"] == []


def test_values_beyond_the_range_played_are_a_warning(tmp_path, capsys):
    """A value of 1e12 was listed as the FAP's range under "no warnings"; the player clamps it."""
    path = tmp_path / "far.fap"
    mask = " ".join("1" if k in (4, 18) else "0" for k in range(68))
    path.write_text(f"2.1 far 25 2\n{mask}\n0 1e12 40\n{mask}\n1 -30 1000\n")
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "warnings (1):" in out
    assert "FAP 5 raise_b_midlip: values -30 .. 1e+12 go beyond the range played, -1860 .. 1860 MNS: clamped" in out


def test_text_summary_names_faps_and_visemes(repo_root, capsys):
    assert main(["inspect", str(repo_root / "fap_streams" / "visemes.fap")]) == 0
    out = capsys.readouterr().out
    assert "48 frames" in out and "1 viseme" in out and "PP" in out and "no warnings" in out


def test_warnings_still_exit_0(tmp_path, capsys):
    path = tmp_path / "w.fap"
    path.write_text("2.0 old 25 5\n" + " ".join(["0", "0", "1"] + ["0"] * 65) + "\n0 120\n")
    assert main(["inspect", str(path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frame_count"] == 1 and summary["declared_frame_count"] == 5 and summary["faps_used"] == [3]
    assert len(summary["warnings"]) == 2


def test_rejected_and_missing_files_exit_2_naming_file_and_line(tmp_path, capsys):
    path = tmp_path / "bad.fap"
    path.write_text("2.1 bad 25 1\n" + " ".join(["0", "0", "1"] + ["0"] * 65) + "\n0 NaN\n")
    assert main(["inspect", str(path), "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and f"{path}:3: token 'NaN'" in captured.err
    assert main(["inspect", str(tmp_path / "missing.fap")]) == 2
    assert "missing.fap: no such file" in capsys.readouterr().err


def test_installed_console_script(repo_root):
    script = Path(sys.executable).with_name("fae")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "fae"]
    result = subprocess.run(command + ["inspect", "--json", str(repo_root / "fap_streams" / "eyes_head.fap")],
                            capture_output=True, text=True, timeout=60, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["faps_used"] == [19, 20, 23, 24, 25, 26, 48, 49, 50] and summary["frame_count"] == 250


def test_the_command_exits_quickly_with_its_status_and_all_its_output(repo_root, tmp_path):
    # `fae` leaves out Python's teardown (fae.cli.run): what it printed still arrives whole,
    # piped, with the command's own exit status, a failure's message included
    script = Path(sys.executable).with_name("fae")
    for command in ([str(script)] if script.exists() else [], [sys.executable, "-m", "fae"]):
        if not command:
            continue
        # (buffered as a user's shell has it, so that the final flush counts)
        env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"} | {"PYTHONWARNINGS": "ignore"}
        done = subprocess.run(command + ["inspect", "--json", str(repo_root / "fap_streams" / "all_faps_sweep.fap")],
                              capture_output=True, text=True, timeout=60, env=env)
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)["frame_count"] > 1000
        bad = tmp_path / "bad.fap"
        bad.write_text("2.1 bad 25 1\n" + " ".join(["0", "0", "1"] + ["0"] * 65) + "\n0 NaN\n")
        done = subprocess.run(command + ["inspect", str(bad)], capture_output=True, text=True, timeout=60, env=env)
        assert done.returncode == 2 and f"{bad}:3: token 'NaN'" in done.stderr


def test_the_command_exits_quickly_after_splitting_warp_launches_over_the_cores():
    # launch_split keeps idle threads for its further ranges; left running, they had made
    # every `fae adapt` take Python's slow teardown. run() lets them go, exits at once with
    # main's status, and a launch after that makes new ones
    script = """
import os, sys, threading
import numpy as np
import fae.cli
from fae.adapt.query import MeshQuery
from fae.cores import workers
from fae.data import shipped_head_path
from fae.io.facemodel_gltf import read_facemodel
from fae.warp_setup import SPLIT_MIN, SPLIT_THREADS, stop_split_pools

exit_now = os._exit
def quick(code):
    print("quick exit", code, flush=True)
    exit_now(code)
os._exit = quick

def split_threads():
    return sum(t.name.startswith("fae-split") for t in threading.enumerate())

head = read_facemodel(shipped_head_path())
query = MeshQuery(head.skin_vertices, head.skin_faces)
X = np.asarray(head.skin_vertices)[np.arange(3 * SPLIT_MIN) % len(head.skin_vertices)] + 0.001
faces = query.closest_points(X)[2]
split = workers(SPLIT_THREADS) > 1
assert split_threads() == (workers(SPLIT_THREADS) - 1 if split else 0), split_threads()
stop_split_pools()
assert split_threads() == 0
assert np.array_equal(query.closest_points(X)[2], faces)  # new pools, the same answers
assert split_threads() == (workers(SPLIT_THREADS) - 1 if split else 0)

def main(argv=None):
    print("main ran", flush=True)
    return 3
fae.cli.main = main
fae.cli.run()
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 3, done.stderr[-2000:]
    assert done.stdout.splitlines() == ["main ran", "quick exit 3"]


@pytest.mark.skipif(os.name != "posix", reason="file size limits and closing descriptors in the child are POSIX")
def test_output_that_cannot_be_written_fails_the_command_and_a_closed_stderr_does_not(repo_root, tmp_path):
    import resource
    import signal

    command = [sys.executable, "-m", "fae", "inspect", "--json", str(repo_root / "fap_streams" / "all_faps_sweep.fap")]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}

    def small_files():  # a disk that fills after 100 bytes
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (100, 100))

    with open(tmp_path / "out.json", "w") as out:
        done = subprocess.run(command, stdout=out, stderr=subprocess.PIPE, text=True, timeout=60, env=env,
                              preexec_fn=small_files)
    assert done.returncode != 0 and "could not write the output" in done.stderr
    # with stderr closed (`2>&-`) a command that starts Warp (whose native line on a missing
    # GPU driver is filtered from stderr) still runs and says what it has to on stdout
    done = subprocess.run([sys.executable, "-m", "fae", "verify-faps", "--faps", "19", "--json"],
                          stdout=subprocess.PIPE, text=True, timeout=120, env=env, preexec_fn=lambda: os.close(2))
    assert done.returncode == 0 and "passed_fraction" in json.loads(done.stdout)


@pytest.mark.parametrize("argv, expected", [
    (["template", "build", "-o", "{tmp}/nowhere/head.glb"], "output folder"),  # was: a traceback after a minute
    (["template", "build", "-o", "{tmp}/head.txt"], "expected a .glb"),
    (["verify-skin", "fap_streams/visemes.fap", "fae/data/generic_head.glb"], "a head among the streams"),
    (["verify-faps", "--faps", ""], "--faps"),  # an empty list checked every FAP
])
def test_commands_refuse_mistyped_arguments_at_once(tmp_path, capsys, argv, expected):
    from fae.cli import main

    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert expected in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_an_output_that_is_a_folder_is_named_not_its_temporary_file(tmp_path):
    from fae.io.atomic import OutputError, atomic_path

    (tmp_path / "manifest.json").mkdir()
    with pytest.raises(OutputError, match=r"manifest.json: cannot be replaced"):
        with atomic_path(tmp_path / "manifest.json") as tmp:
            tmp.write_text("{}")
    assert [p.name for p in tmp_path.iterdir()] == ["manifest.json"]  # no temporary file left


def test_a_header_rate_too_slow_to_play_is_refused_naming_it(tmp_path, capsys):
    """A header rate of 1e-320 frames/s gave an infinite duration (`"duration_s": Infinity`
    in --json, which strict readers refuse), and `fae export` overflowed its key times into
    a traceback: a rate below 0.001 frames/s is no rate a stream plays at."""
    stream = tmp_path / "slow.fap"
    mask = " ".join(["0", "0", "1"] + ["0"] * 65)
    stream.write_text(f"2.1 slow 1e-320 1\n{mask}\n0 100\n")
    assert main(["inspect", "--json", str(stream)]) == 2
    err = capsys.readouterr().err
    assert "slow.fap:1" in err and "1e-320" in err and "frames per second in [0.001, 10000]" in err
