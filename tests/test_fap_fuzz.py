"""Whatever bytes a user hands fae, the .fap reader either understands them or raises
FapFormatError: mutate real streams at the byte, line and token level and check that no
other exception escapes (reading, dense frames, inspect summary)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given
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

byte_edit = st.tuples(st.just("byte"), st.integers(0, 1 << 20), st.binary(min_size=0, max_size=4),
                      st.integers(0, 4))
line_edit = st.tuples(st.just("line"), st.integers(0, 1 << 20), st.sampled_from(["drop", "dup", "swap", "insert"]),
                      st.sampled_from([b"", b"# note", b"2.1 x 25 1", b"1 " * 69, b"0 " * 68, b"\xff\xfe", b"0 1 2"]))
token_edit = st.tuples(st.just("token"), st.integers(0, 1 << 20), st.sampled_from(NASTY_TOKENS) | st.text(max_size=6),
                       st.booleans())


def _mutate(data: bytes, edit) -> bytes:
    kind, where, what, extra = edit
    if kind == "byte":
        i = where % (len(data) + 1)
        return data[:i] + what + data[i + extra:]
    lines = data.split(b"\n")
    i = where % len(lines)
    if kind == "line":
        if what == "drop":
            del lines[i]
        elif what == "dup":
            lines.insert(i, lines[i])
        elif what == "swap" and i + 1 < len(lines):
            lines[i], lines[i + 1] = lines[i + 1], lines[i]
        else:
            lines.insert(i, extra)
        return b"\n".join(lines)
    tokens = lines[i].split(b" ")
    j = (where // len(lines)) % len(tokens)
    token = what.encode("utf-8", "surrogatepass") if isinstance(what, str) else what
    if extra:
        tokens[j] = token
    else:
        tokens.insert(j, token)
    lines[i] = b" ".join(tokens)
    return b"\n".join(lines)


_TMP = Path(tempfile.mkdtemp(prefix="fae-fap-fuzz-"))


@given(seed=st.integers(0, len(SEEDS) - 1),
       edits=st.lists(st.one_of(byte_edit, line_edit, token_edit), min_size=1, max_size=4),
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
