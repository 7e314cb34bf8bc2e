"""The manifest of a batch: every job, its inputs with checksums, and what became of it.

OUT_DIR/manifest.json is rewritten (atomically) each time a job ends, so an interrupted
run leaves an accurate one. A job's entry:

    output         file name in OUT_DIR          origin   where the job list named it
    inputs         {"stream": {"path", "sha256"}, "head": {"path", "sha256"}}
    view, size, fps
    status         "done" (rendered in this run), "skipped" (kept from an earlier run),
                   "failed" (every attempt failed), "pending" (not finished: interrupted)
    frames, seconds (on the worker, head set-up included), worker (its address)
    attempts       how many times it was tried in this run; errors: each failed try's reason
    error          the last reason, for a failed job
    output_sha256  checksum of the video written
    head_reused    the worker had the head set up already (from an earlier job)

A rerun keeps (skips) an output whose earlier entry was done or skipped with the same
input checksums and settings and whose file still has the recorded checksum.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from fae.batch.jobs import Job, file_sha256
from fae.io.atomic import atomic_open

MANIFEST_NAME = "manifest.json"
FORMAT = 1


def new_entry(job: Job) -> dict:
    return {
        "output": job.output,
        "origin": job.origin,
        "inputs": {"stream": {"path": str(job.stream), "sha256": job.stream_sha256},
                   "head": {"path": str(job.head), "sha256": job.head_sha256}},
        "view": job.view,
        "size": f"{job.size[0]}x{job.size[1]}",
        "fps": job.fps,
        "status": "pending",
        "frames": None,
        "seconds": None,
        "worker": None,
        "attempts": 0,
        "errors": [],
        "error": None,
        "output_sha256": None,
        "warnings": [],
    }


def _entry_settings(entry: dict) -> dict:
    # an earlier manifest edited by hand may hold anything where a table was: then it matches nothing
    inputs = entry.get("inputs") if isinstance(entry.get("inputs"), dict) else {}
    stream = inputs.get("stream") if isinstance(inputs.get("stream"), dict) else {}
    head = inputs.get("head") if isinstance(inputs.get("head"), dict) else {}
    return {"stream_sha256": stream.get("sha256"), "head_sha256": head.get("sha256"),
            "view": entry.get("view"), "size": entry.get("size"), "fps": entry.get("fps")}


def read_previous(out_dir: str | os.PathLike) -> dict[str, dict]:
    """Entries of the manifest an earlier run left in `out_dir`, by output name ({} when
    there is none or it cannot be read: then everything is rendered again)."""
    path = Path(out_dir) / MANIFEST_NAME
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return {e["output"]: e for e in data.get("jobs", []) if isinstance(e, dict) and "output" in e}
    except (OSError, ValueError, TypeError, AttributeError):
        return {}


def kept_entry(job: Job, previous: dict | None, out_dir: str | os.PathLike) -> dict | None:
    """The entry to carry over when the job's earlier output can be kept, else None."""
    if not previous or previous.get("status") not in ("done", "skipped"):
        return None
    if _entry_settings(previous) != job.settings():
        return None
    video = Path(out_dir) / job.output
    try:
        if not video.is_file() or file_sha256(video) != previous.get("output_sha256"):
            return None
    except OSError:
        return None
    entry = new_entry(job)
    for key in ("frames", "seconds", "worker", "output_sha256", "warnings"):
        entry[key] = previous.get(key)
    entry["status"] = "skipped"
    return entry


def write_manifest(out_dir: str | os.PathLike, header: dict, entries: list[dict]) -> Path:
    """Write OUT_DIR/manifest.json atomically; returns its path."""
    counts = {s: sum(1 for e in entries if e["status"] == s) for s in ("done", "skipped", "failed", "pending")}
    path = Path(out_dir) / MANIFEST_NAME
    document = {"format": FORMAT, **header, "summary": {"jobs": len(entries), **counts}, "jobs": entries}
    with atomic_open(path, "w", encoding="utf-8") as handle:
        json.dump(document, handle, indent=2)
        handle.write("\n")
    return path
