"""The job list of `fae batch`: what to render, read from a CSV or JSON file or a glob.

    load_jobs(source, heads=[], defaults=JobDefaults()) -> list[Job]

`source` is
  - a .csv file: a header row naming some of the columns stream, head, view, size, fps,
    output (stream is required; an empty cell takes the default), then one job a row;
  - a .json file: a list of objects with the same keys (or {"jobs": [...]});
  - anything else: a glob of .fap files (`corpus/*.fap`), each played on every head given
    (`heads`, the shipped generic head when none).
Relative paths in a job file are read from the file's own folder, so a job file moves with
its streams. Every file is read here (its checksum goes into the manifest), so a missing
stream or head stops the batch before anything runs; a file that is there but cannot be
played fails its own job on the worker.

Anything wrong raises JobFileError with a one-line message naming the file, the line (CSV)
or job number (JSON) and the field, and what was expected.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from fae.io.fap import MIN_FPS

COLUMNS = ("stream", "head", "view", "size", "fps", "output")
MAX_SIDE = 8192


class JobFileError(ValueError):
    """The job list cannot be used; the message names where and why."""


@dataclass(frozen=True)
class JobDefaults:
    """What a job gets for a field its row leaves out (the command line's options)."""

    view: str = "front"
    size: tuple[int, int] = (640, 480)
    fps: float | None = None


@dataclass(frozen=True)
class Job:
    """One video to render.

    stream, head   absolute paths of the inputs (the shipped generic head when none was named)
    stream_sha256, head_sha256   their checksums when the list was read
    view, size, fps   camera preset, (width, height), frame rate (None: the stream's)
    output         file name of the video inside the output folder
    origin         where the job was written ("jobs.csv:4", "jobs.json job 3", a glob)
    """

    stream: Path
    head: Path
    stream_sha256: str
    head_sha256: str
    view: str
    size: tuple[int, int]
    fps: float | None
    output: str
    origin: str = field(default="", compare=False)

    def settings(self) -> dict:
        """Everything that decides the video's content besides the input files' paths."""
        return {"stream_sha256": self.stream_sha256, "head_sha256": self.head_sha256, "view": self.view,
                "size": f"{self.size[0]}x{self.size[1]}", "fps": self.fps}


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _views() -> tuple[str, ...]:
    from fae.render.framing import VIEWS

    return tuple(VIEWS)


def size_numbers(text: str) -> tuple[int, int] | None:
    """'640x480' -> (640, 480), any size; None unless it is WIDTHxHEIGHT in ASCII digits (int()
    also takes "1_0", "+64" and other scripts' digits: 64_0x48 was a 640x48 video)."""
    match = re.fullmatch(r"\s*([0-9]{1,6})[xX]([0-9]{1,6})\s*", text)
    return None if match is None else (int(match[1]), int(match[2]))


def parse_size_text(text: str) -> tuple[int, int] | None:
    """'640x480' -> (640, 480); None when it is not an even WIDTHxHEIGHT within 2..8192."""
    size = size_numbers(text)
    if size is None:
        return None
    w, h = size
    if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE) or w % 2 or h % 2:
        return None
    return w, h


class _Checksums:
    """Reads each input file once, however many jobs name it."""

    def __init__(self):
        self._known: dict[Path, str] = {}

    def __call__(self, path: Path) -> str:
        if path not in self._known:
            self._known[path] = file_sha256(path)
        return self._known[path]


def _resolve(where: str, name: str, value: str, base: Path, suffix: str, checksums: _Checksums) -> tuple[Path, str]:
    path = Path(value).expanduser()
    if not path.is_absolute():
        path = base / path
    path = path.resolve()
    if path.suffix.lower() != suffix:
        raise JobFileError(f"{where}: field '{name}' {value!r}: expected a {suffix} file")
    if not path.is_file():
        raise JobFileError(f"{where}: field '{name}' {value!r}: file not found ({path})")
    try:
        return path, checksums(path)
    except OSError as exc:
        raise JobFileError(f"{where}: field '{name}' {value!r}: cannot read it ({exc.strerror or exc})") from None


def _output_name(where: str, value: str) -> str:
    name = value.strip()
    if not name or Path(name).name != name or name in (".", "..") or name.startswith("."):
        raise JobFileError(f"{where}: field 'output' {value!r}: expected a plain file name such as talk.mp4 "
                           "(written inside the output folder)")
    if Path(name).suffix.lower() != ".mp4":
        raise JobFileError(f"{where}: field 'output' {value!r}: expected a .mp4 file name")
    return name


def _job(where: str, record: dict, base: Path, defaults: JobDefaults, default_head: Path | None,
         checksums: _Checksums, shipped: tuple[Path, str]) -> Job:
    def text(name: str) -> str:
        value = record.get(name)
        if value is None:
            return ""
        if isinstance(value, bool) or not isinstance(value, (str, int, float)):
            raise JobFileError(f"{where}: field '{name}' {value!r}: expected text")
        value = str(value).strip()
        if any(ord(c) < 32 or ord(c) == 127 for c in value):  # no path or file name holds a NUL or a newline
            raise JobFileError(f"{where}: field '{name}' {value!r}: expected text without control characters")
        return value

    stream_text = text("stream")
    if not stream_text:
        raise JobFileError(f"{where}: field 'stream' is empty: expected a .fap file")
    stream, stream_sha = _resolve(where, "stream", stream_text, base, ".fap", checksums)
    head_text = text("head")
    if head_text:
        head, head_sha = _resolve(where, "head", head_text, base, ".glb", checksums)
    elif default_head is not None:
        head, head_sha = default_head, checksums(default_head)
    else:
        head, head_sha = shipped
    view = text("view") or defaults.view
    if view not in _views():
        raise JobFileError(f"{where}: field 'view' {view!r}: expected one of {', '.join(_views())}")
    size_text = text("size")
    size = defaults.size
    if size_text:
        size = parse_size_text(size_text)
        if size is None:
            raise JobFileError(f"{where}: field 'size' {size_text!r}: expected WIDTHxHEIGHT in pixels, both even "
                               f"and at most {MAX_SIDE}, e.g. 640x480")
    fps_text = text("fps")
    fps = defaults.fps
    if fps_text:
        try:
            fps = float(fps_text)
        except ValueError:
            fps = math.nan
        if not (MIN_FPS <= fps <= 1000):
            raise JobFileError(f"{where}: field 'fps' {fps_text!r}: expected a frame rate in [{MIN_FPS:g}, 1000], "
                               "or nothing for the stream's own")
    output_text = text("output")
    output = _output_name(where, output_text) if output_text else f"{stream.stem}.mp4"
    return Job(stream=stream, head=head, stream_sha256=stream_sha, head_sha256=head_sha, view=view, size=size,
               fps=fps, output=output, origin=where)


def _shipped_head() -> Path:
    from fae.data import shipped_head_path

    return shipped_head_path()


def _csv_records(path: Path) -> list[tuple[str, dict]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise JobFileError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    rows = list(csv.reader(text.splitlines()))
    numbered = [(i + 1, row) for i, row in enumerate(rows) if any(cell.strip() for cell in row)
                and not row[0].lstrip().startswith("#")]
    if not numbered:
        raise JobFileError(f"{path}: no header row: expected columns {', '.join(COLUMNS)} (stream required)")
    header_line, header = numbered[0]
    names = [cell.strip().lower() for cell in header]
    for name in names:
        if name not in COLUMNS:
            raise JobFileError(f"{path}:{header_line}: unknown column {name!r}: expected a header row of "
                               f"{', '.join(COLUMNS)} (stream required)")
    if "stream" not in names:
        raise JobFileError(f"{path}:{header_line}: no 'stream' column: expected a header row of "
                           f"{', '.join(COLUMNS)} (stream required)")
    duplicated = {n for n in names if names.count(n) > 1}
    if duplicated:
        raise JobFileError(f"{path}:{header_line}: column {sorted(duplicated)[0]!r} appears twice")
    records = []
    for line, row in numbered[1:]:
        if len(row) > len(names):
            raise JobFileError(f"{path}:{line}: {len(row)} fields: expected at most {len(names)} "
                               f"({', '.join(names)})")
        records.append((f"{path}:{line}", dict(zip(names, row))))
    return records


def _json_records(path: Path) -> list[tuple[str, dict]]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise JobFileError(f"{path}:{exc.lineno}: not JSON ({exc.msg}): expected a list of jobs") from None
    except UnicodeDecodeError as exc:
        raise JobFileError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    if isinstance(data, dict) and "jobs" in data:
        data = data["jobs"]
    if not isinstance(data, list):
        raise JobFileError(f"{path}: expected a list of jobs (objects with {', '.join(COLUMNS)}), "
                           f"or {{\"jobs\": [...]}}")
    records = []
    for number, item in enumerate(data, 1):
        where = f"{path} job {number}"
        if not isinstance(item, dict):
            raise JobFileError(f"{where}: expected an object with {', '.join(COLUMNS)}, got {type(item).__name__}")
        unknown = [k for k in item if k not in COLUMNS]
        if unknown:
            raise JobFileError(f"{where}: unknown field {unknown[0]!r}: expected {', '.join(COLUMNS)}")
        records.append((where, item))
    return records


def load_jobs(source: str, heads: list[str] | None = None, defaults: JobDefaults = JobDefaults()) -> list[Job]:
    """The jobs named by `source` (see the module docstring); raises JobFileError."""
    checksums = _Checksums()
    shipped_path = _shipped_head()
    shipped: tuple[Path, str] | None = None

    def shipped_head() -> tuple[Path, str]:
        nonlocal shipped
        if shipped is None:
            if not shipped_path.is_file():
                raise JobFileError(f"{shipped_path}: the shipped generic head is not there "
                                   "(name a head in the job list or with --head)")
            shipped = (shipped_path, checksums(shipped_path))
        return shipped

    head_paths: list[Path] = []
    for text in heads or []:
        head_paths.append(_resolve("--head", "head", text, Path.cwd(), ".glb", checksums)[0])

    path = Path(source)
    suffix = path.suffix.lower()
    if suffix in (".csv", ".json") and not any(c in source for c in "*?["):
        if not path.is_file():
            raise JobFileError(f"{source}: job file not found")
        records = _csv_records(path) if suffix == ".csv" else _json_records(path)
        if not records:
            raise JobFileError(f"{source}: no jobs in the file")
        if len(head_paths) > 1:
            raise JobFileError(f"--head given {len(head_paths)} times: a job file takes one default head "
                               "(name others in its 'head' column)")
        default_head = head_paths[0] if head_paths else None
        base = path.resolve().parent
        jobs = []
        for where, record in records:
            needs_shipped = not str(record.get("head") or "").strip() and default_head is None
            jobs.append(_job(where, record, base, defaults, default_head, checksums,
                             shipped_head() if needs_shipped else (Path(), "")))
    else:
        streams = sorted(Path(p) for p in glob.glob(os.path.expanduser(source), recursive=True))
        streams = [p for p in streams if p.suffix.lower() == ".fap" and p.is_file()]
        if not streams:
            raise JobFileError(f"{source}: no .fap files match (expected a .csv or .json job list, "
                               "or a glob of .fap files)")
        heads_to_use: list[Path | None] = list(head_paths) or [None]
        jobs = []
        for stream in streams:
            for head in heads_to_use:
                record = {"stream": str(stream.resolve())}
                if head is not None:
                    record["head"] = str(head)
                    if len(heads_to_use) > 1:  # one video per stream and head
                        record["output"] = f"{stream.stem}-{head.stem}.mp4"
                jobs.append(_job(f"{source} ({stream.name})", record, Path.cwd(), defaults, None, checksums,
                                 shipped_head() if head is None else (Path(), "")))
    seen: dict[str, str] = {}
    for job in jobs:
        if job.output in seen:
            raise JobFileError(f"{job.origin}: field 'output' {job.output!r}: already the output of "
                               f"{seen[job.output]}; expected a name of its own")
        seen[job.output] = job.origin
    return jobs
