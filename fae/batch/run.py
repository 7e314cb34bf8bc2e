"""Run batch jobs on Dask distributed: an embedded LocalCluster, or the scheduler given.

    run_batch(jobs, out_dir, scheduler=None, workers=None, retries=2) -> BatchResult

Without a scheduler address a LocalCluster of worker processes starts on 127.0.0.1 (one
per two cores: one job's pipeline, simulation and rendering threads plus ffmpeg, keeps
about two cores busy, and on two cores one worker made 0.29-0.31 videos/s against
0.22-0.26 for two; one thread each, math libraries and the OSMesa rasterizer held to one thread,
so that workers do not fight over cores) and stops when the batch ends. With an address
(tcp://HOST:8786) the jobs go to that cluster; its workers need fae installed and nothing
else from this machine: each job carries its stream's bytes, each head is sent once to
every worker (scattered), and the video comes back as bytes that this process writes into
OUT_DIR (temporary file, then rename), so a half-written video never appears.

Each job is one Dask task calling fae.batch.worker.render_job; when a try fails (the
stream or head cannot be played, the worker was lost) it is submitted again, up to
`retries` more times, and then reported with its reason while the other jobs go on. The
manifest (fae.batch.manifest) is rewritten after every job.
"""

from __future__ import annotations

import hashlib
import logging
import os
import sys
import time
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

from fae.batch.jobs import Job, file_sha256
from fae.batch.manifest import kept_entry, new_entry, read_previous, write_manifest
from fae.cores import usable_cores
from fae.io.atomic import atomic_path

# Each worker process renders with one thread; parallelism comes from the processes.
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                  "LP_NUM_THREADS": "1"}
CONNECT_TIMEOUT_S = 20
HANDSHAKE_TIMEOUT_S = 5.0  # a scheduler greets a new connection at once


class ClusterError(RuntimeError):
    """The cluster could not be started or reached; the message says which and why."""


@dataclass
class BatchResult:
    entries: list[dict]
    manifest: Path
    seconds: float
    scheduler: str
    counts: dict = field(default_factory=dict)

    @property
    def failed(self) -> list[dict]:
        return [e for e in self.entries if e["status"] == "failed"]


def default_workers() -> int:
    """Worker processes of the embedded cluster: one per two usable cores (at least one)."""
    return max(1, usable_cores() // 2)


def _render_on_worker(spec: dict, stream_bytes: bytes, head_bytes: bytes) -> dict:
    """The task a worker runs: one job, plus which worker ran it."""
    # A user's `dask worker` may not set them; only the rasterizer's is read late enough
    # (when the first renderer is made) for this to count, the others help child processes.
    for name, value in ONE_THREAD_ENV.items():
        os.environ.setdefault(name, value)
    from distributed import get_worker

    from fae.batch.worker import JobFailed, render_job

    try:
        result = render_job(spec, stream_bytes, head_bytes)
    except JobFailed as exc:  # an answer, not a crash: no traceback in the worker's log
        result = {"error": " ".join(str(exc).split())}  # one line (an encoder's message spans several)
    result["worker"] = get_worker().address
    return result


def _reason(exc: BaseException) -> str:
    """One line for the manifest: why a try failed."""
    kind = type(exc).__name__
    if kind == "KilledWorker":
        last = getattr(exc, "last_worker", None)
        address = getattr(last, "address", last)
        return f"worker {address} lost while rendering" if address else "a worker was lost while rendering"
    if kind in ("CancelledError", "FutureCancelledError"):
        return f"cancelled: the worker or its data was lost ({exc})" if str(exc) else "cancelled: the worker was lost"
    text = " ".join(str(exc).split())
    return f"{kind}: {text}" if text else kind


def _not_a_scheduler(address: str) -> str | None:
    """Why a tcp:// `address` is no Dask scheduler, or None (also for other schemes, left to
    Dask): a scheduler sends its handshake as soon as it accepts, a length-prefixed frame.
    Dask's own connection waited for ever on a listener that says nothing until asked (a web
    server, `fae serve`'s native side)."""
    import socket
    import struct

    if not address.startswith("tcp://"):
        return None
    host, _, port = address[len("tcp://"):].rpartition(":")
    if not host or not port.isdigit():
        return "expected tcp://HOST:PORT"
    try:
        with socket.create_connection((host.strip("[]") or "127.0.0.1", int(port)), timeout=CONNECT_TIMEOUT_S) as s:
            s.settimeout(HANDSHAKE_TIMEOUT_S)
            first = b""
            while len(first) < 8:
                chunk = s.recv(8 - len(first))
                if not chunk:
                    return "it closed the connection without a word"
                first += chunk
    except socket.timeout:
        return f"it said nothing within {HANDSHAKE_TIMEOUT_S:g} s of the connection, as a scheduler does at once"
    except (OSError, ValueError) as exc:
        return " ".join(str(exc).split()) or type(exc).__name__
    if not 0 < struct.unpack("<Q", first)[0] < 1 << 30:
        return f"it answered {first!r}, not a Dask handshake"
    return None


def _start_client(scheduler: str | None, workers: int | None):
    """(client, cluster or None, address in words)."""
    from distributed import Client, LocalCluster

    if scheduler:
        problem = _not_a_scheduler(scheduler)
        if problem:
            raise ClusterError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there ({problem})")
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise ClusterError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there "
                               f"({' '.join(str(exc).split()) or type(exc).__name__})") from None
        return client, None, scheduler
    count = workers or default_workers()
    try:
        cluster = LocalCluster(n_workers=count, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, silence_logs=logging.CRITICAL, env=dict(ONE_THREAD_ENV))
    except Exception as exc:  # noqa: BLE001 - any start-up failure is reported, not traced
        raise ClusterError(f"cannot start the embedded Dask cluster ({type(exc).__name__}: {exc})") from None
    return Client(cluster), cluster, f"embedded LocalCluster, {count} worker process{'es' if count > 1 else ''}"


def _spec(job: Job) -> dict:
    return {"stream": str(job.stream), "head": str(job.head), "head_sha256": job.head_sha256, "view": job.view,
            "size": list(job.size), "fps": job.fps, "output": job.output}


def run_batch(jobs: list[Job], out_dir: str | os.PathLike, scheduler: str | None = None,
              workers: int | None = None, retries: int = 2, source: str = "",
              progress: bool | None = None, log: Callable[[str], None] | None = None) -> BatchResult:
    """Render `jobs` into `out_dir` (which must exist); see the module docstring.

    progress  a tqdm bar on stderr (None: when stderr is a terminal)
    log       called with a line per finished job when there is no bar (None: stderr)
    Raises ClusterError when the cluster cannot be started or reached.
    """
    out = Path(out_dir)
    started = time.perf_counter()
    header = {"source": source, "out_dir": str(out.resolve()),
              "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "scheduler": None, "retries": retries}
    previous = read_previous(out)
    entries = []
    todo: list[int] = []
    for index, job in enumerate(jobs):
        kept = kept_entry(job, previous.get(job.output), out)
        entries.append(kept or new_entry(job))
        if kept is None:
            todo.append(index)
    if progress is None:
        progress = sys.stderr.isatty()
    say = log or (lambda line: print(line, file=sys.stderr))

    def save() -> Path:
        return write_manifest(out, header, entries)

    if not todo:
        header["scheduler"] = "none needed: every output was kept"
        header["finished"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        path = save()
        return BatchResult(entries, path, time.perf_counter() - started, header["scheduler"], _counts(entries))

    client, cluster, where = _start_client(scheduler, workers)
    header["scheduler"] = where if cluster is not None else scheduler
    save()
    bar = None
    frames_done = 0
    try:
        from distributed import as_completed

        heads: dict[str, object] = {}  # head checksum -> scattered bytes (a Future)
        head_bytes: dict[str, bytes] = {}

        def head_future(job: Job):
            future = heads.get(job.head_sha256)
            if future is None or future.status != "finished":  # first use, or lost with its workers
                if job.head_sha256 not in head_bytes:
                    data = job.head.read_bytes()
                    if hashlib.sha256(data).hexdigest() != job.head_sha256:
                        raise OSError(f"{job.head}: changed since the job list was read")
                    head_bytes[job.head_sha256] = data
                future = client.scatter(head_bytes[job.head_sha256], broadcast=True, hash=False)
                heads[job.head_sha256] = future
            return future

        run_token = uuid.uuid4().hex[:8]
        owner: dict[str, int] = {}  # task key -> job index

        def submit(index: int):
            job = jobs[index]
            entries[index]["attempts"] += 1
            try:
                stream_bytes = job.stream.read_bytes()
                if hashlib.sha256(stream_bytes).hexdigest() != job.stream_sha256:
                    raise OSError(f"{job.stream}: changed since the job list was read")
                head = head_future(job)
            except OSError as exc:
                return None, str(exc) if exc.filename is None else f"{exc.filename}: cannot read it ({exc.strerror})"
            key = f"fae-batch-{run_token}-{index}-{entries[index]['attempts']}"
            future = client.submit(_render_on_worker, _spec(job), stream_bytes, head, key=key, pure=False, retries=0)
            owner[future.key] = index
            return future, None

        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(todo), unit="job", desc="fae batch", file=sys.stderr)
        pending = as_completed()
        failures = 0

        def advance_bar() -> None:
            rate = frames_done / max(time.perf_counter() - started, 1e-9)
            done = sum(1 for e in entries if e["status"] == "done")
            bar.set_postfix_str(f"done {done}, failed {failures}, {rate:.0f} frames/s", refresh=False)
            bar.update(1)

        def finish_failed(index: int, reason: str, retry: bool = True) -> None:
            nonlocal failures
            entry = entries[index]
            entry["errors"].append(reason)
            if retry and entry["attempts"] <= retries:
                future, problem = submit(index)
                if future is not None:
                    pending.add(future)
                    return
                entry["errors"].append(problem)  # the input itself is unreadable now: no more tries
            entry["status"] = "failed"
            entry["error"] = entry["errors"][-1]
            failures += 1
            save()
            if bar is not None:
                advance_bar()
            else:
                say(f"{entry['output']}: failed after {entry['attempts']} "
                    f"{'try' if entry['attempts'] == 1 else 'tries'}: {entry['error']}")

        for index in todo:
            future, problem = submit(index)
            if future is None:
                finish_failed(index, problem, retry=False)
            else:
                pending.add(future)
        for future in pending:
            index = owner.pop(future.key)
            entry = entries[index]
            job = jobs[index]
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - every failure of a try is recorded, not raised
                finish_failed(index, _reason(exc))
                future.release()
                continue
            future.release()
            if "error" in result:
                entry["worker"] = result["worker"]  # the last worker that tried it
                finish_failed(index, result["error"])
                continue
            target = out / job.output
            try:
                with atomic_path(target) as tmp:
                    tmp.write_bytes(result["video"])
            except OSError as exc:
                # the output folder, not the job: another try would fail the same way
                finish_failed(index, f"{target}: cannot write the video ({exc.strerror or exc})", retry=False)
                continue
            entry.update(status="done", frames=result["frames"], seconds=round(result["seconds"], 3),
                         worker=result["worker"], error=None, output_sha256=file_sha256(target),
                         warnings=result["warnings"], head_reused=result["head_reused"])
            frames_done += result["frames"]
            save()
            if bar is not None:
                advance_bar()
            else:
                say(f"{job.output}: {result['frames']} frames in {result['seconds']:.1f} s on {result['worker']}")
    finally:
        if bar is not None:
            bar.close()
        header["finished"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        header["frames_per_second"] = round(frames_done / max(time.perf_counter() - started, 1e-9), 2)
        save()
        client.close()
        if cluster is not None:
            cluster.close()
    path = Path(out) / "manifest.json"
    return BatchResult(entries, path, time.perf_counter() - started, header["scheduler"], _counts(entries))


def _counts(entries: list[dict]) -> dict:
    return {s: sum(1 for e in entries if e["status"] == s) for s in ("done", "skipped", "failed", "pending")}
