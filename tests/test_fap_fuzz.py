"""Whatever bytes a user hands fae, the .fap reader either understands them or raises
FapFormatError: mutate real streams at the byte, line and token level and check that no
other exception escapes (reading, dense frames, inspect summary)."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fae.io.fap import FapFormatError, FapParser, read_fap
from fae.io.frames import dense_frames

REPO = Path(__file__).resolve().parent.parent
SHARED_FAP = REPO.parent / "shared" / "data" / "fap"
SEED_LINES = 31  # header + 15 frames: enough structure, small enough for ~10k examples in CI


def _seeds() -> list[bytes]:
    paths = sorted((REPO / "fap_streams").glob("*.fap"))
    if SHARED_FAP.is_dir():
        paths += sorted(SHARED_FAP.glob("*.fap"))
    seeds = []
    for path in paths:
        with open(path, "rb") as handle:
            seeds.append(b"".join(handle.readline() for _ in range(SEED_LINES)))
    return seeds


SEEDS = _seeds()
NASTY_TOKENS = ["nan", "NaN", "inf", "-inf", "1e999", "-1e309", "9" * 400, "0x1F", "1_000", "", "#", "+", "-",
                ".", "1.", ".5", "1e5", "2.0", "2.2", "69", "-0", "\x00", "\u0661\u0662", "\ufeff", "é", "1 1",
                "\r", "\t", "63", "64", "14", "15", "0 0 0 0", "3.0"]

LINE_INSERTS = [b"", b"# note", b"2.1 x 25 1", b"1 " * 69, b"0 " * 68, b"\xff\xfe", b"0 1 2", b"\t\r"]
LINE_OPS = ["drop", "dup", "swap", "insert"]

# One edit = (kind 0 byte / 1 line / 2 token, position, choice, replace?, bytes): flat
# tuples of cheap primitives keep generation fast enough for 10,000 examples.
edit = st.tuples(st.integers(0, 2), st.integers(0, 1 << 20), st.integers(0, 1 << 10), st.booleans(),
                 st.binary(max_size=4))


def _mutate(data: bytes, edit) -> bytes:
    kind, where, choice, replace, raw = edit
    if kind == 0:  # bytes: insert or overwrite up to 4 raw bytes, or delete some
        i = where % (len(data) + 1)
        return data[:i] + raw + data[i + (choice % 5 if replace else 0):]
    lines = data.split(b"\n")
    i = where % len(lines)
    if kind == 1:
        op = LINE_OPS[choice % len(LINE_OPS)]
        if op == "drop":
            del lines[i]
        elif op == "dup":
            lines.insert(i, lines[i])
        elif op == "swap" and i + 1 < len(lines):
            lines[i], lines[i + 1] = lines[i + 1], lines[i]
        else:
            lines.insert(i, LINE_INSERTS[choice % len(LINE_INSERTS)])
        return b"\n".join(lines)
    tokens = lines[i].split(b" ")
    j = (where // len(lines)) % len(tokens)
    token = NASTY_TOKENS[choice % len(NASTY_TOKENS)].encode("utf-8") if choice % 3 else raw
    if replace:
        tokens[j] = token
    else:
        tokens.insert(j, token)
    lines[i] = b" ".join(tokens)
    return b"\n".join(lines)


# Memory-backed when the machine has it: a disk write per example would dominate the run.
_TMP = Path(tempfile.mkdtemp(prefix="fae-fap-fuzz-", dir="/dev/shm" if Path("/dev/shm").is_dir() else None))
atexit.register(shutil.rmtree, _TMP, ignore_errors=True)


@given(seed=st.integers(0, len(SEEDS) - 1),
       edits=st.lists(edit, min_size=1, max_size=4),
       crlf=st.booleans())
def test_only_fap_format_errors_escape(seed, edits, crlf):
    data = SEEDS[seed]
    for edit in edits:
        data = _mutate(data, edit)
    if crlf:
        data = data.replace(b"\n", b"\r\n")
    path = _TMP / "mutant.fap"
    path.write_bytes(data)
    try:
        stream = read_fap(path)
        frames = list(dense_frames(stream, fps=stream.header.fps * 1.5, fill=True))
        assert all(np.all(np.isfinite(f.values)) for f in frames)
        assert all(isinstance(w, str) for w in stream.warnings)
    except FapFormatError as error:
        assert error.path == str(path) and error.line >= 0 and str(error).startswith(str(path))


# Lines straight into the push parser: cheap to check but costly to generate, so a tenth
# of the profile's examples.
@settings(max_examples=max(50, settings.default.max_examples // 10))
@given(st.lists(st.binary(max_size=80) | st.text(max_size=80), max_size=6))
def test_push_parser_raises_only_format_errors(lines):
    parser = FapParser("socket")
    try:
        parser.feed_line("2.1 live 25 0", 1)
        for number, line in enumerate(lines, start=2):
            text = line.decode("latin-1") if isinstance(line, bytes) else line
            parser.feed_line(text, number)
        parser.finish()
    except FapFormatError as error:
        assert error.path == "socket"
