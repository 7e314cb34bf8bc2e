"""The job list of `fae batch` (CSV, JSON, glob x heads), what a rerun keeps, and the
command's answers to bad input: one line naming the file, line and field, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from batch_support import short_stream
from fae.batch.jobs import JobDefaults, JobFileError, file_sha256, load_jobs
from fae.batch.manifest import kept_entry, new_entry
from fae.cli import main
from fae.data import shipped_head_path

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture()
def corpus(tmp_path):
    (tmp_path / "streams").mkdir()
    for name in ("hello", "world"):
        short_stream(tmp_path / "streams" / f"{name}.fap", 4)
    (tmp_path / "other.glb").write_bytes(b"not really a head, but a file with a checksum")
    return tmp_path


def test_csv_rows_take_defaults_and_read_paths_from_the_files_folder(corpus, monkeypatch):
    (corpus / "jobs.csv").write_text(
        "# corpus of two\n"
        "stream,head,view,size,fps,output\n"
        "streams/hello.fap,,,,,\n"
        "\n"
        "streams/world.fap,other.glb,profile,320x240,12.5,world-profile.mp4\n")
    monkeypatch.chdir("/")
    jobs = load_jobs(str(corpus / "jobs.csv"), defaults=JobDefaults(size=(160, 120)))
    hello, world = jobs
    assert hello.stream == corpus / "streams" / "hello.fap"
    assert hello.head == shipped_head_path()
    assert (hello.view, hello.size, hello.fps, hello.output) == ("front", (160, 120), None, "hello.mp4")
    assert hello.stream_sha256 == file_sha256(corpus / "streams" / "hello.fap")
    assert world.head == corpus / "other.glb" and world.head_sha256 == file_sha256(corpus / "other.glb")
    assert (world.view, world.size, world.fps, world.output) == ("profile", (320, 240), 12.5, "world-profile.mp4")
    assert world.origin.endswith("jobs.csv:5")


def test_json_lists_and_glob_times_heads(corpus, monkeypatch):
    (corpus / "jobs.json").write_text(json.dumps({"jobs": [
        {"stream": "streams/hello.fap", "size": "64x48"},
        {"stream": "streams/world.fap", "head": "other.glb", "fps": 30}]}))
    jobs = load_jobs(str(corpus / "jobs.json"))
    assert [j.output for j in jobs] == ["hello.mp4", "world.mp4"]
    assert jobs[0].size == (64, 48) and jobs[1].fps == 30.0

    monkeypatch.chdir(corpus)
    shipped_copy = corpus / "generic.glb"
    shipped_copy.write_bytes(shipped_head_path().read_bytes())
    jobs = load_jobs("streams/*.fap", heads=["generic.glb", "other.glb"], defaults=JobDefaults(view="profile"))
    assert sorted(j.output for j in jobs) == ["hello-generic.mp4", "hello-other.mp4", "world-generic.mp4",
                                              "world-other.mp4"]
    assert all(j.view == "profile" for j in jobs)
    assert [j.output for j in load_jobs("streams/*.fap")] == ["hello.mp4", "world.mp4"]


@pytest.mark.parametrize("rows, expected", [
    ("stream,size\nstreams/hello.fap,64x\n", r"jobs.csv:2: field 'size' '64x': expected WIDTHxHEIGHT"),
    ("stream,size\nstreams/hello.fap,6_4x48\n", r"jobs.csv:2: field 'size' '6_4x48': expected WIDTHxHEIGHT"),
    ("stream,size\nstreams/hello.fap,65x48\n", r"jobs.csv:2: field 'size' '65x48': expected .*even"),
    ("\n# c\nstream,colour\n", r"jobs.csv:3: unknown column 'colour': expected .*stream, head, view"),
    ("head\nother.glb\n", r"jobs.csv:1: no 'stream' column"),
    ("stream\nstreams/hello.fap\nstreams/missing.fap\n", r"jobs.csv:3: field 'stream' 'streams/missing.fap': file not found"),
    ("stream,view\nstreams/hello.fap,top\n", r"jobs.csv:2: field 'view' 'top': expected one of front, three-quarter, profile"),
    ("stream,fps\nstreams/hello.fap,fast\n", r"jobs.csv:2: field 'fps' 'fast': expected a frame rate"),
    ("stream,fps\nstreams/hello.fap,0\n", r"jobs.csv:2: field 'fps' '0': expected a frame rate"),
    # accepted, it reached ffmpeg as a rate of 0/1: a job failed with five lines of its log
    ("stream,fps\nstreams/hello.fap,0.0001\n", r"jobs.csv:2: field 'fps' '0.0001': expected a frame rate in \[0.001"),
    ("stream,output\nstreams/hello.fap,../x.mp4\n", r"jobs.csv:2: field 'output' '../x.mp4': expected a plain file name"),
    ("stream,output\nstreams/hello.fap,x.avi\n", r"jobs.csv:2: field 'output' 'x.avi': expected a .mp4 file name"),
    ("stream,output\nstreams/hello.fap,a.mp4\nstreams/world.fap,a.mp4\n",
     r"jobs.csv:3: field 'output' 'a.mp4': already the output of .*jobs.csv:2"),
    ("stream,head\nstreams/hello.fap,other.obj\n", r"jobs.csv:2: field 'head' 'other.obj': expected a .glb file"),
    ("stream\nstreams/hello.fap,extra\n", r"jobs.csv:2: 2 fields: expected at most 1"),
    ("stream\n", r"jobs.csv: no jobs in the file"),
    ("stream,output\nstreams/hel\0lo.fap,x.mp4\n", r"jobs.csv:2: field 'stream' .*without control characters"),
    ("", r"jobs.csv: no header row"),
])
def test_bad_csv_names_file_line_and_field(corpus, rows, expected):
    (corpus / "jobs.csv").write_text(rows)
    with pytest.raises(JobFileError, match=expected):
        load_jobs(str(corpus / "jobs.csv"))


@pytest.mark.parametrize("text, expected", [
    ('[{"stream": "streams/hello.fap",}]', r"jobs.json:1: not JSON"),
    ('{"stream": "streams/hello.fap"}', r"jobs.json: expected a list of jobs"),
    ('[{"stream": "streams/hello.fap"}, "world"]', r"jobs.json job 2: expected an object"),
    ('[{"stream": "streams/hello.fap", "zoom": 2}]', r"jobs.json job 1: unknown field 'zoom'"),
    ('[{"stream": ["streams/hello.fap"]}]', r"jobs.json job 1: field 'stream' .*: expected text"),
    ('[{"size": "64x48"}]', r"jobs.json job 1: field 'stream' is empty"),
    # a NUL in a path raised Python's ValueError from Path.resolve (a traceback); in an
    # output name it reached the worker, which blamed the stream
    ('[{"stream": "streams/hel\\u0000lo.fap"}]', r"jobs.json job 1: field 'stream' .*: expected text without control"),
    ('[{"stream": "streams/hello.fap", "head": "g\\u0000.glb"}]', r"jobs.json job 1: field 'head' .*without control"),
    ('[{"stream": "streams/hello.fap", "output": "a\\u0000b.mp4"}]', r"jobs.json job 1: field 'output' .*without control"),
    ('[{"stream": "streams/hello.fap", "output": "a\\nb.mp4"}]', r"jobs.json job 1: field 'output' .*without control"),
])
def test_bad_json_names_file_job_and_field(corpus, text, expected):
    (corpus / "jobs.json").write_text(text)
    with pytest.raises(JobFileError, match=expected):
        load_jobs(str(corpus / "jobs.json"))


def test_glob_that_matches_nothing_and_heads_that_are_not_there(corpus, monkeypatch):
    monkeypatch.chdir(corpus)
    with pytest.raises(JobFileError, match=r"nope/\*\.fap: no \.fap files match"):
        load_jobs("nope/*.fap")
    with pytest.raises(JobFileError, match=r"--head: field 'head' 'gone.glb': file not found"):
        load_jobs("streams/*.fap", heads=["gone.glb"])


def test_a_rerun_keeps_only_outputs_whose_inputs_and_file_are_unchanged(corpus):
    (corpus / "jobs.csv").write_text("stream,size\nstreams/hello.fap,64x48\n")
    out = corpus / "out"
    out.mkdir()
    (job,) = load_jobs(str(corpus / "jobs.csv"))
    video = out / job.output
    video.write_bytes(b"a video")
    entry = new_entry(job) | {"status": "done", "frames": 4, "worker": "tcp://127.0.0.1:1",
                              "output_sha256": file_sha256(video)}
    kept = kept_entry(job, entry, out)
    assert kept["status"] == "skipped" and kept["frames"] == 4 and kept["attempts"] == 0
    assert kept_entry(job, entry | {"status": "failed"}, out) is None
    assert kept_entry(job, entry | {"size": "640x480"}, out) is None  # asked for another size
    assert kept_entry(job, None, out) is None
    short_stream(corpus / "streams" / "hello.fap", 5)  # the stream changed since
    (changed,) = load_jobs(str(corpus / "jobs.csv"))
    assert kept_entry(changed, entry, out) is None
    video.write_bytes(b"a video, edited")  # the file is not the one written
    assert kept_entry(job, entry, out) is None
    # a manifest edited by hand: inputs that are no table were a traceback (AttributeError)
    for inputs in (3, {"stream": "x"}, {"stream": {"sha256": 1}, "head": []}):
        assert kept_entry(job, entry | {"inputs": inputs}, out) is None


def fae_batch(*args, cwd):
    return subprocess.run([sys.executable, "-m", "fae", "batch", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=120)


def test_command_rejects_bad_input_with_one_line_and_status_2(corpus, monkeypatch, capsys):
    (corpus / "jobs.csv").write_text("stream,size\nstreams/hello.fap,160x120\nstreams/world.fap,big\n")
    result = fae_batch("jobs.csv", "-o", "out", cwd=corpus)
    assert result.returncode == 2
    assert result.stderr.strip() == ("fae batch: jobs.csv:3: field 'size' 'big': expected WIDTHxHEIGHT in pixels, "
                                     "both even and at most 8192, e.g. 640x480")
    assert not (corpus / "out").exists()  # nothing started
    for args, expected in [
        (["streams/*.fap", "-o", "out", "--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"], "--workers sizes"),
        (["streams/*.fap", "-o", "out", "--scheduler", "127.0.0.1:8786"], "expected an address such as tcp://"),
        (["streams/*.fap", "-o", "out", "--scheduler", "tcp://127.0.0.1"], "(expected tcp://HOST:PORT)"),
        (["streams/*.fap", "-o", "out", "--retries", "-1"], "--retries -1: expected 0..100"),
        (["streams/*.fap", "-o", "out", "--view", "top"], "--view 'top': expected one of"),
        (["streams/*.fap", "-o", "other.glb"], "other.glb: is a file, expected the output folder"),
        (["missing.csv", "-o", "out"], "missing.csv: job file not found"),
    ]:
        monkeypatch.chdir(corpus)
        assert main(["batch", *args]) == 2, args
        stderr = capsys.readouterr().err
        assert stderr.startswith("fae batch: ") and expected in stderr
        assert len(stderr.strip().splitlines()) == 1


def test_a_scheduler_address_where_something_else_listens_is_refused_at_once(corpus):
    """Case: `--scheduler` pointed at a web server (or `fae serve`) hung for ever: Dask's
    connection waited for a handshake that never came. A scheduler greets a connection at
    once; a listener that says nothing is refused within seconds, naming why."""
    import socket
    import threading

    (corpus / "jobs.csv").write_text("stream,size\nstreams/hello.fap,64x48\n")
    listener = socket.create_server(("127.0.0.1", 0))
    held = []

    def accept():
        while True:
            try:
                held.append(listener.accept()[0])  # held open, silent
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    try:
        port = listener.getsockname()[1]
        result = fae_batch("jobs.csv", "-o", "out", "--scheduler", f"tcp://127.0.0.1:{port}", cwd=corpus)
    finally:
        listener.close()
        for conn in held:
            conn.close()
    assert result.returncode == 2
    assert "cannot reach a Dask scheduler there (it said nothing within 5 s" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
