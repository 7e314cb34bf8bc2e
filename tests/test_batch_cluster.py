"""`fae batch` on a real Dask cluster: a `dask scheduler` and two `dask worker` processes on
127.0.0.1; one worker is killed while the batch runs. Every good job still gets its video
with the stream's frame count, the bad stream is reported with its reason, the manifest
lists every job; a rerun renders nothing again."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from batch_support import bad_stream, short_stream, tinted_head, video_frames

pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parent.parent
DASK = [sys.executable, "-m", "dask"]  # the `dask` command of this environment


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def child_env(tmp: Path) -> dict:
    env = dict(os.environ)
    # the killed worker cannot remove its job folder (nor Dask its scratch space): both go
    # under the test's own folder, not the machine's /tmp
    scratch = tmp / "tmp"
    scratch.mkdir(exist_ok=True)
    env["TMPDIR"] = str(scratch)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", LP_NUM_THREADS="1", PYOPENGL_PLATFORM="osmesa")
    # A lost worker comes back to fae as a failed try (retried by fae) rather than being
    # rescheduled by Dask on its own: the path this test is about.
    env["DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES"] = "0"
    return env


def wait_for_port(port: int, proc: subprocess.Popen, seconds: float = 60) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        assert proc.poll() is None, "the Dask process exited while starting"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise AssertionError(f"nothing listens on port {port}")


class Cluster:
    """A scheduler and workers, each in its own session (a worker's nanny and its child die together)."""

    def __init__(self, tmp: Path):
        self.env = child_env(tmp)
        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.log = open(tmp / "cluster.log", "wb")
        self.scheduler = self._start(["scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                                      "--no-dashboard"])
        wait_for_port(self.port, self.scheduler)
        self.workers: dict[int, subprocess.Popen] = {}

    def _start(self, args: list[str]) -> subprocess.Popen:
        return subprocess.Popen([*DASK, *args], cwd=REPO, env=self.env, stdout=self.log, stderr=subprocess.STDOUT,
                                start_new_session=True)

    def add_worker(self) -> int:
        port = free_port()
        self.workers[port] = self._start(["worker", self.address, "--host", "127.0.0.1",
                                          "--worker-port", str(port), "--nthreads", "1", "--nworkers", "1",
                                          "--no-dashboard", "--memory-limit", "0"])
        return port

    def kill_worker(self, port: int) -> None:
        proc = self.workers.pop(port)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()

    def close(self) -> None:
        for proc in [*self.workers.values(), self.scheduler]:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in [*self.workers.values(), self.scheduler]:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        self.log.close()


def wait_for_workers(address: str, count: int, seconds: float = 90) -> None:
    from distributed import Client

    with Client(address, timeout="30s") as client:
        client.wait_for_workers(count, timeout=seconds)


def manifest_of(out: Path) -> dict:
    try:
        return json.loads((out / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_batch_on_a_cluster_survives_a_lost_worker_and_resumes(tmp_path):
    streams = tmp_path / "streams"
    streams.mkdir()
    frames = {"a": 10, "b": 14, "c": 18, "d": 22, "e": 12, "f": 16, "g": 20}
    for name, count in frames.items():
        short_stream(streams / f"{name}.fap", count)
    bad_stream(streams / "broken.fap")
    tinted_head(tmp_path / "tinted.glb")
    rows = ["stream,head,view,size,output"]
    for name in "abcd":  # the shipped head
        rows.append(f"streams/{name}.fap,,{'profile' if name == 'd' else 'front'},160x120,{name}.mp4")
    for name in "efg":
        rows.append(f"streams/{name}.fap,tinted.glb,three-quarter,160x120,{name}-tinted.mp4")
    rows.append("streams/broken.fap,tinted.glb,,160x120,broken.mp4")
    (tmp_path / "jobs.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "out"

    cluster = Cluster(tmp_path)
    try:
        for _ in range(2):
            cluster.add_worker()
        wait_for_workers(cluster.address, 2)
        command = [sys.executable, "-m", "fae", "batch", str(tmp_path / "jobs.csv"), "-o", str(out),
                   "--scheduler", cluster.address, "--retries", "2"]
        batch = subprocess.Popen(command, cwd=tmp_path, env=cluster.env, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        # Mid-run: as soon as one video is in, kill the worker that made it (it is busy
        # with the next job, and holds a copy of the heads).
        victim = None
        while victim is None and batch.poll() is None:
            done = [e for e in manifest_of(out).get("jobs", []) if e["status"] == "done"]
            if done:
                victim = int(done[0]["worker"].rsplit(":", 1)[1])
            else:
                time.sleep(0.1)
        assert victim is not None, "the batch ended before any video was in: nothing left to kill a worker under"
        cluster.kill_worker(victim)
        stdout, stderr = batch.communicate(timeout=240)
        assert batch.returncode == 1, stderr  # one job failed

        manifest = manifest_of(out)
        entries = {e["output"]: e for e in manifest["jobs"]}
        assert len(entries) == 8 and manifest["summary"]["jobs"] == 8
        assert manifest["summary"]["done"] == 7 and manifest["summary"]["failed"] == 1
        for name, count in frames.items():
            output = f"{name}.mp4" if name in "abcd" else f"{name}-tinted.mp4"
            entry = entries[output]
            assert entry["status"] == "done", entry
            assert video_frames(out / output) == count == entry["frames"]
            assert entry["inputs"]["stream"]["sha256"] and entry["inputs"]["head"]["sha256"]
            assert entry["worker"].startswith("tcp://127.0.0.1:")
        heads = {entries[o]["inputs"]["head"]["sha256"] for o in ("a.mp4", "e-tinted.mp4")}
        assert len(heads) == 2
        assert not (out / "broken.mp4").exists()
        broken = entries["broken.mp4"]
        assert broken["status"] == "failed" and broken["attempts"] == 3
        assert "broken.fap:2" in broken["error"] and "nonsense" in broken["error"]
        assert "broken.mp4" in stderr and "nonsense" in stderr and "Traceback" not in stderr
        # The jobs the killed worker held (a running one, and one queued: Dask gives a
        # one-thread worker two) came back as failed tries and were done on the other.
        lost = [e for e in entries.values() if any(f"worker tcp://127.0.0.1:{victim} lost" in r for r in e["errors"])]
        assert lost and all(e["status"] == "done" and e["worker"] != f"tcp://127.0.0.1:{victim}" for e in lost)
        assert not list(out.glob(".*.mp4")), "a temporary video was left behind"

        # Rerun on what is left of the cluster: every video is kept, the bad job tried again.
        mtimes = {p.name: p.stat().st_mtime_ns for p in out.glob("*.mp4")}
        rerun = subprocess.run(command, cwd=tmp_path, env=cluster.env, capture_output=True, text=True, timeout=240)
        assert rerun.returncode == 1, rerun.stderr
        again = {e["output"]: e for e in manifest_of(out)["jobs"]}
        assert {o for o, e in again.items() if e["status"] == "skipped"} == set(mtimes)
        assert again["broken.mp4"]["status"] == "failed"
        assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.mp4")} == mtimes
        assert "0 rendered, 7 kept" in rerun.stderr
    finally:
        cluster.close()
