"""`fae play` against hostile streams and a hostile environment: a trillion-frame gap,
SIGTERM/SIGINT/SIGKILL mid-run, an output folder that takes no files. Every wait is bounded."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fae.cli import main
from fae.io.atomic import OutputError, atomic_path, sweep_stale

REPO = Path(__file__).resolve().parents[1]
LONG_STREAM = REPO / "fap_streams" / "all_faps_sweep.fap"  # 1,656 frames: long enough to interrupt
SHORT_STREAM = REPO / "fap_streams" / "visemes.fap"


def jaw_frame(number: int, value: int) -> str:
    mask = ["0"] * 68
    mask[2] = "1"
    return " ".join(mask) + f"\n{number} {value}\n"


def fae_play(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-m", "fae", "play", *args, "--size", "64x48"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def hidden_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def wait_for_temporary_video(folder: Path, proc: subprocess.Popen, seconds: float = 120) -> None:
    deadline = time.monotonic() + seconds
    while not hidden_files(folder):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "fae play never started its video"
        time.sleep(0.05)
    time.sleep(0.5)  # frames are being encoded into it


@pytest.mark.slow
def test_a_trillion_frame_gap_is_held_for_max_hold_seconds_with_a_warning(tmp_path):
    """Case: frames 0 and 10**12 used to play for ever. The gap is now held 60 s (the
    default --max-hold), the video ends, and the user is told."""
    stream = tmp_path / "gap.fap"
    stream.write_text("2.1 gap 1 2\n" + jaw_frame(0, 100) + jaw_frame(10 ** 12, 900))
    proc = fae_play(str(stream), "-o", str(tmp_path / "gap.mp4"))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert (f"fae play: warning: {stream}: frames 1..999999999999 are missing (1e+12 s): frame 0 is held for 60 s "
            "only, and the stream goes on from there") in err
    assert "gap.mp4: 62 frames at 1 fps" in err  # frame 0, 60 held, the last
    assert (tmp_path / "gap.mp4").stat().st_size > 0


@pytest.mark.slow
def test_sigterm_removes_the_half_written_video(tmp_path):
    """Case: SIGTERM mid-run left a hidden partial .mp4 beside the output. (SIGINT takes the
    same way out, as KeyboardInterrupt.)"""
    out = tmp_path / "out.mp4"
    proc = fae_play(str(LONG_STREAM), "-o", str(out))
    wait_for_temporary_video(tmp_path, proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and "fae: terminated" in err
    assert list(tmp_path.iterdir()) == []  # no video, no temporary file


@pytest.mark.slow
def test_a_killed_runs_temporary_video_is_swept_by_the_next_run(tmp_path):
    out = tmp_path / "out.mp4"
    proc = fae_play(str(LONG_STREAM), "-o", str(out))
    wait_for_temporary_video(tmp_path, proc)
    proc.kill()  # SIGKILL: nothing can clean up
    proc.communicate(timeout=60)
    left = hidden_files(tmp_path)
    assert len(left) == 1 and left[0].startswith(f".out.mp4.{proc.pid}.")
    again = fae_play(str(SHORT_STREAM), "-o", str(out))
    _, err = again.communicate(timeout=300)
    assert again.returncode == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mp4"]


def test_temporary_files_of_running_writers_and_of_other_outputs_are_not_swept(tmp_path):
    target = tmp_path / "a.glb"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".a.glb.{int(dead.stdout)}.abcd1234.glb"
    alive = tmp_path / f".a.glb.{os.getppid()}.abcd1234.glb"  # a running process
    other = tmp_path / f".b.glb.{int(dead.stdout)}.abcd1234.glb"  # another output's
    for p in (stale, alive, other):
        p.write_bytes(b"partial")
    with atomic_path(target) as tmp:
        assert tmp.name.startswith(f".a.glb.{os.getpid()}.")
        tmp.write_bytes(b"whole")
    assert not stale.exists() and alive.exists() and other.exists() and target.read_bytes() == b"whole"
    assert sweep_stale(tmp_path / "b.glb") == [other]


def test_an_output_that_is_a_pipe_is_refused_and_a_link_is_replaced_not_followed(tmp_path, capsys):
    """Case: `fae render -o PIPE.png` (and, as root, `fae adapt ... -o /dev/null`) renamed a
    plain file over the pipe or device. A named pipe is refused in one line, before any work
    and by the writer itself; an output that is a link is replaced by the file, the file it
    pointed to left alone (a link planted in a shared folder cannot aim fae at a user's file)."""
    from fae.cli import main

    pipe = tmp_path / "frame.png"
    os.mkfifo(pipe)
    assert main(["render", "-o", str(pipe), "--size", "64x48"]) == 2
    assert "is a named pipe, not a file" in capsys.readouterr().err
    with pytest.raises(OutputError, match="named pipe"):
        with atomic_path(pipe) as tmp:
            tmp.write_bytes(b"x")
    assert pipe.is_fifo()
    real = tmp_path / "real.json"
    real.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(real)
    with atomic_path(link) as tmp:
        tmp.write_text("new")
    assert not link.is_symlink() and link.read_text() == "new" and real.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.png", "link.json", "real.json"]


def test_an_output_folder_that_takes_no_files_is_one_line_naming_it(capsys):
    """Case: `-o /proc/x.mp4` gave a FileNotFoundError traceback (root may write anywhere
    os.access can tell; /proc still takes no files)."""
    if not Path("/proc").is_dir():
        pytest.skip("no /proc")
    assert main(["play", str(SHORT_STREAM), "-o", "/proc/x.mp4"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("fae play: /proc/x.mp4: output folder /proc ")
    assert "Traceback" not in err



def test_an_output_named_as_an_input_is_refused_and_the_input_kept(tmp_path, capsys):
    """`fae play clip.mp4 -o clip.mp4` (a stream saved under a video's name) replaced the
    stream with the video, exit 0; the head and its landmarks are inputs too."""
    stream = tmp_path / "clip.mp4"
    stream.write_bytes(SHORT_STREAM.read_bytes())
    assert main(["play", str(stream), "-o", str(stream)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "would overwrite the stream" in err
    assert stream.read_bytes() == SHORT_STREAM.read_bytes()
    head = tmp_path / "head.mp4"
    head.write_bytes(b"not read")
    assert main(["play", str(SHORT_STREAM), "--head", str(head), "-o", str(head)]) == 2
    assert "would overwrite the --head" in capsys.readouterr().err and head.read_bytes() == b"not read"


def test_a_stream_without_frames_is_refused_and_leaves_nothing(tmp_path):
    """A header and no frame line gave a ValueError traceback (exit 1)."""
    stream = tmp_path / "empty.fap"
    stream.write_text("2.1 empty 25 0\n")
    proc = fae_play(str(stream), "-o", str(tmp_path / "e.mp4"), "--frames-dir", str(tmp_path / "frames"))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, err
    assert "empty.fap: no frames to play" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.fap"]  # no video, no frames folder


def test_frames_dir_keeps_its_frames_when_a_run_fails_and_takes_a_good_runs_whole(tmp_path):
    """A stream broken part-way left the frames rendered before the break beside the
    error; a shorter stream played into a folder used before left the old run's last
    frames mixed in."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "frame_00099.png").write_bytes(b"an earlier run's")
    (frames / "frame_cover.png").write_bytes(b"the user's own")  # not a frame: kept
    (frames / f".frames.{2**22 + 7}.dead_run").mkdir()  # a killed run's staging (no such process): swept
    (frames / ".frames.2024.backup").mkdir()  # the user's own (not a pid and 8 random letters): kept
    broken = tmp_path / "broken.fap"
    broken.write_text("".join(SHORT_STREAM.read_text().splitlines(keepends=True)[:60]) + "junk\n")
    proc = fae_play(str(broken), "-o", str(tmp_path / "b.mp4"), "--frames-dir", str(frames))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 2 and "no video written" in err, err
    kept = [".frames.2024.backup"]
    assert sorted(p.name for p in frames.iterdir()) == kept + ["frame_00099.png", "frame_cover.png"]  # nothing added
    proc = fae_play(str(SHORT_STREAM), "-o", str(tmp_path / "v.mp4"), "--frames-dir", str(frames))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    names = sorted(p.name for p in frames.iterdir())
    count = int(err.strip().splitlines()[-1].split(": ")[1].split()[0])  # "<out>: 48 frames at ..."
    assert names == kept + [f"frame_{i:05d}.png" for i in range(count)] + ["frame_cover.png"]


def test_the_readers_warnings_are_shown(tmp_path):
    """A frame dropped at the end of the file, and a header that declares more frames than
    the body holds, were said by `fae inspect` only."""
    stream = tmp_path / "short.fap"
    stream.write_text("2.1 short 25 2\n" + jaw_frame(0, 100) + " ".join(["0"] * 68) + "\n")
    proc = fae_play(str(stream), "-o", str(tmp_path / "s.mp4"))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "warning: " in err and "mask line without a values line" in err and "declares 2 frames" in err


@pytest.mark.parametrize("args, expected", [
    (["render", "-o", "x.png", "--size", "5800x5800", "--supersample", "4"], "too large"),
    (["render", "-o", "x.png", "--size", "100x6000", "--supersample", "8"], "at most 16384 pixels a side"),
    (["play", str(SHORT_STREAM), "-o", "x.mp4", "--size", "8192x100", "--supersample", "3"], "at most 16384 pixels"),
    (["play", str(SHORT_STREAM), "-o", "x.mp4", "--fps", "0.0001"], "--fps 0.0001: expected a frame rate in"),
    (["bake", "-o", "x.glb", "--faps", "3-300000000"], "expected FAP numbers (1-68)"),
    # refused once the whole stream had been rendered, as the video could not replace the folder
    (["play", str(SHORT_STREAM), "-o", "q.mp4", "--frames-dir", "q.mp4"], "--frames-dir q.mp4: the same path as -o"),
])
def test_settings_out_of_reach_are_one_line_naming_them(tmp_path, capsys, monkeypatch, args, expected):
    """A 23200x23200 render killed the process (SIGSEGV), and any side past 16384 drew a
    squashed head (exit 0) or died at 65536; a rate of 0.0001 frames/s reached
    ffmpeg as 0/1 (exit 1); a typo'd range of FAPs built a list of 300 million."""
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert expected in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("size", ["64_0x48", "+64x48", "\uff16\uff14x48", "64 x 48"])
def test_a_size_is_ascii_digits_only(tmp_path, capsys, monkeypatch, size):
    """int() took "64_0x48" (a 640x48 video), "+64x48" and other scripts' digits."""
    monkeypatch.chdir(tmp_path)
    for args in (["play", str(SHORT_STREAM), "-o", "x.mp4"], ["render", "-o", "x.png"]):
        with pytest.raises(SystemExit) as stop:
            main([*args, "--size", size])
        assert stop.value.code == 2 and "expected WIDTHxHEIGHT" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_fap_list_names_each_fap_once():
    """`--faps 3,3` baked two tables for FAP 3, which then moved the jaw twice as far."""
    from fae.commands.verify_faps import parse_fap_list

    assert parse_fap_list("3,3-5,4,19") == [3, 4, 5, 19]
    for bad in ("0", "69", "5-3", "x"):
        with pytest.raises(ValueError, match="--faps"):
            parse_fap_list(bad)


def test_a_users_file_named_like_a_temporary_one_is_not_swept(tmp_path):
    """The sweep took `.face.glb.20241105.final.glb` (a user's file: a date, a word) for a
    dead writer's temporary file and deleted it; a temporary name is the pid (at most 7
    digits) and tempfile's 8 random characters."""
    users = tmp_path / ".face.glb.20241105.final.glb"
    users.write_bytes(b"mine")
    stale = tmp_path / f".face.glb.{2**22 + 7}.k3j9_x0q.glb"  # no such process
    stale.write_bytes(b"half written")
    assert sweep_stale(tmp_path / "face.glb") == [stale]
    assert users.read_bytes() == b"mine"


@pytest.mark.parametrize("command", ["render", "play"])
def test_a_render_that_runs_out_of_memory_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch, command):
    """`fae render --size 8192x8192 --supersample 2` passes the size guard but holds about
    10 GB; under a memory limit it ended in a numpy traceback (exit 1)."""
    from fae.render.renderer import FaceRenderer

    def no_memory(self, *args, **kwargs):
        raise MemoryError("Unable to allocate 2.00 GiB")

    monkeypatch.setattr(FaceRenderer, "render_rgba", no_memory)
    out = tmp_path / ("big.png" if command == "render" else "big.mp4")
    argv = ["render", "-o", str(out)] if command == "render" else ["play", str(SHORT_STREAM), "-o", str(out)]
    assert main([*argv, "--size", "4096x4096", "--supersample", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"fae {command}: --size 4096x4096 with --supersample 2: not enough memory")
    assert not out.exists() and "Traceback" not in "\n".join(err)


def test_a_full_disk_names_the_output_and_leaves_nothing(tmp_path):
    """A write that fails for want of space said only "[Errno 28] No space left on device"
    (fae export) or ended in a traceback (fae render): which file it was is the message."""
    with pytest.raises(OutputError, match=r"out\.glb: cannot be written \(No space left on device\)"):
        with atomic_path(tmp_path / "out.glb") as tmp:
            tmp.write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_render_on_a_full_disk_is_one_line_and_sweeps_dead_temporaries(tmp_path, capsys, monkeypatch):
    from PIL import Image

    stale = tmp_path / f".x.png.{2**22 + 7}.k3j9_x0q.png"  # a killed render's, no such process
    stale.write_bytes(b"half written")

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", full)
    out = tmp_path / "x.png"
    assert main(["render", "-o", str(out), "--size", "64x48"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out}: cannot be written (No space left on device)" in err
    assert list(tmp_path.iterdir()) == []  # nothing half-written, and the dead render's temporary swept
