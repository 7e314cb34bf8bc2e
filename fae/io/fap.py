"""Reading and writing MPEG-4 .fap text streams.

Format (one header, then two lines per frame)::

    2.1 name with spaces 25 108          version, name, fps, declared frame count
    0 0 1 1 ... (68 tokens)              mask: 1 = FAP sent in this frame
    0 10 10 -3 ...                       frame number, then one value per masked FAP

Values are in FAPU (or AU = 1e-5 rad) as the standard defines them. When the mask selects
FAP 1 the values line carries either one token or the four viseme fields
(select1 select2 blend def); for FAP 2 one token or the six expression fields
(select1 intensity1 select2 intensity2 init_face def). The form is told apart by the
number of tokens on the line: the totals 1+1, 4+1, 1+6 and 4+6 are all distinct, so only
a line that fits no form is rejected. A single FAP 1 token 0..14 is read as that viseme
alone (blend 63), a single FAP 2 token 0..6 as that expression at full intensity; other
single tokens are kept as values with a warning. ``values[0]`` / ``values[1]`` hold the
selected viseme / expression code (select1).

What real files do, and what fae does with it:

- versions 2.1 and 2.2 are read as they are. Version 2.0 is read the same way, with a
  warning: older writers are said to have scaled values differently, but no public
  decoder or document found shows a different scale (Xface reads every version alike and
  divides by the same FAPU), so fae does not rescale; a wrong guess would silently distort
  every stream. Other versions are rejected.
- CRLF line ends, tabs, blank lines, ``#`` comment lines anywhere and ``#`` comments after
  the tokens of a mask or values line; a UTF-8 byte-order mark; names that are not UTF-8
  (read as Latin-1, with a warning).
- 69-token masks (writers that keep an unused slot 0 for 1-based FAP numbering and write
  the whole 69-entry array): the leading slot is dropped when it is 0. The values line
  cannot tell a leading from a trailing extra slot (both drop a 0), so a trailing 0 is
  dropped only when the leading token is 1 (which no unused slot would be); one warning.
- frame numbers from 0 or 1; gaps are allowed (one warning; the player holds the values
  over the missing frames); numbers must increase.
- names with spaces (everything between the version and the last two header tokens);
  integer or float fps; a declared frame count that disagrees with the body (warning).
- a frame whose mask line is the last line of the file is dropped with a warning.

Everything else raises :class:`FapFormatError` naming the file, line, token and what was
expected; no other exception escapes the reader, whatever the input bytes.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fae.io.atomic import atomic_path
from fae.mpeg4.faps import FAP_COUNT
from fae.mpeg4.highlevel import (
    BLEND_MAX,
    EXPRESSION_SELECT_MAX,
    VISEME_SELECT_MAX,
    Expression,
    Viseme,
)

__all__ = [
    "FapFormatError", "FapHeader", "FapFrame", "FapParser", "FapStream", "Viseme", "Expression",
    "read_fap", "write_fap", "format_header", "format_frame", "SUPPORTED_VERSIONS",
]

SUPPORTED_VERSIONS = ("2.0", "2.1", "2.2")
WRITE_VERSION = "2.1"
MAX_LINE_BYTES = 1 << 16  # a values line of 68 FAPs needs ~1 KiB; anything far longer is not a .fap
_MAX_FPS = 10_000.0
MIN_FPS = 0.001  # frames/s played or recorded: a video's rate is a fraction whose denominator is at most 1001
_MAX_NUMBER = 1e15  # larger frame numbers or counts are not real streams (and lose integer precision)
_VISEME_TOKENS = 4
_EXPRESSION_TOKENS = 6
# ASCII only: Python's \d also takes other scripts' digits ("１２３"), which no .fap writer means.
_INT_RE = re.compile(r"[+-]?\d+\Z", re.ASCII)
# Unambiguous (the digits before a point belong to one group), so a failing match backtracks
# in linear, not quadratic, time on a long hostile token.
_NUMBER_RE = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\Z", re.ASCII)
# Characters a decimal number may hold: a values line made only of these is converted in one
# call (no regex, so no backtracking on hostile input); anything else takes the per-token path.
_NUMBER_CHARS = frozenset("0123456789+-.eE")


class FapFormatError(ValueError):
    """A .fap stream that fae cannot understand.

    path      file name (or the stream's source name)
    line      1-based line number (0 when the problem is the file as a whole)
    token     the offending token, or None when the line as a whole is at fault
    expected  what fae expected there
    """

    def __init__(self, path: str, line: int, token: str | None, expected: str):
        self.path = str(path)
        self.line = int(line)
        self.token = token
        self.expected = expected
        shown = token if token is None or len(token) <= 40 else token[:37] + "..."
        where = f"{self.path}:{self.line}" if self.line > 0 else self.path
        super().__init__(f"{where}: expected {expected}" if token is None else f"{where}: token {shown!r}: expected {expected}")


@dataclass(frozen=True)
class FapHeader:
    """The first line of a .fap stream.

    version               as written (``"2.0" | "2.1" | "2.2"``)
    name                  free text (may hold spaces; "" when absent)
    fps                   frames per second, in [MIN_FPS, 10000]
    declared_frame_count  the count the header claims (the body may differ)
    """

    version: str
    name: str
    fps: float
    declared_frame_count: int


@dataclass(eq=False)
class FapFrame:
    """One frame as the stream gives it.

    number      frame number as written (from 0 or 1, may skip)
    mask        (68,) bool, FAP number-1: sent in this frame
    values      (68,) float64, FAP number-1, FAPU / AU units as written; 0 where unmasked;
                [0] / [1] hold the viseme / expression select1 code when FAP 1 / 2 is sent
    viseme      FAP 1 record when sent in a form fae understands, else None
    expression  FAP 2 record when sent in a form fae understands, else None
    """

    number: int
    mask: np.ndarray
    values: np.ndarray
    viseme: Viseme | None = None
    expression: Expression | None = None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FapFrame):
            return NotImplemented
        return (self.number == other.number and np.array_equal(self.mask, other.mask)
                and np.array_equal(self.values, other.values)
                and self.viseme == other.viseme and self.expression == other.expression)


def _decode(raw: bytes) -> tuple[str, bool]:
    try:
        return raw.decode("utf-8"), True
    except UnicodeDecodeError:
        return raw.decode("latin-1"), False


class FapParser:
    """Push parser: feed it lines one at a time, get frames back as they complete.

    >>> parser = FapParser("socket")
    >>> frame = parser.feed_line(text, line_number)   # FapFrame | None
    >>> parser.finish()                                # at end of stream

    ``header`` is None until the header line has been read; ``warnings`` collects what
    was accepted with a warning. Every problem raises :class:`FapFormatError`.

    max_line  characters one line may hold (its line end included); a longer line is
              refused before any of it is split, so a caller feeding unbounded lines
              cannot make the parser allocate for them
    """

    def __init__(self, source_name: str = "<stream>", max_line: int = MAX_LINE_BYTES):
        self.source_name = str(source_name)
        self.max_line = int(max_line)
        self.header: FapHeader | None = None
        self.warnings: list[str] = []
        self.frame_count = 0
        self._mask_tokens: list[str] | None = None
        self._mask_line = 0
        self._last_number: int | None = None
        self._warned: set[str] = set()

    @classmethod
    def after_header(cls, source_name: str, header: "FapHeader", warned: Iterable[str] = (),
                     warnings: list[str] | None = None, max_line: int = MAX_LINE_BYTES) -> "FapParser":
        """A parser that resumes a stream whose header was read already (by another parser):
        it expects frame lines. warned: the keys of the warnings given once already (see
        `warned_keys`), so that they are not repeated; warnings: the list to append to."""
        parser = cls(source_name, max_line=max_line)
        parser.header = header
        parser._warned = set(warned)
        if warnings is not None:
            parser.warnings = warnings
        return parser

    @property
    def warned_keys(self) -> frozenset[str]:
        """Keys of the warnings given once so far (for `after_header`)."""
        return frozenset(self._warned)

    def warn_once(self, key: str, message: str) -> None:
        """Add `message` (prefixed with the source's name) to `warnings` unless a warning with
        the same `key` was given already."""
        self._warn_once(key, message)

    # -- helpers -----------------------------------------------------------------
    def _error(self, line: int, token: str | None, expected: str) -> FapFormatError:
        return FapFormatError(self.source_name, line, token, expected)

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.warnings.append(f"{self.source_name}: {message}")

    def _number(self, token: str, line: int, what: str) -> float:
        if not _NUMBER_RE.match(token):
            raise self._error(line, token, f"{what} (a finite decimal number)")
        value = float(token)
        if not math.isfinite(value):
            raise self._error(line, token, f"{what} (a finite decimal number)")
        return value

    def _integer(self, token: str, line: int, what: str, low: int, high: float) -> int:
        if not _INT_RE.match(token) or len(token) > 20:
            raise self._error(line, token, f"{what} (an integer {low}..{high:g})")
        value = int(token)
        if not low <= value <= high:
            raise self._error(line, token, f"{what} (an integer {low}..{high:g})")
        return value

    # -- lines -------------------------------------------------------------------
    def feed_line(self, line: str, line_number: int) -> FapFrame | None:
        """Parse one line (its end-of-line characters may be included).

        Returns the frame completed by this line (a values line), else None.
        """
        if len(line) > self.max_line:
            raise self._error(line_number, None, f"a line of at most {self.max_line} characters, "
                              f"got {len(line)}")
        if line.startswith("\ufeff") and self.header is None:
            line = line[1:]
        text = line.rstrip("\r\n")
        if "\r" in text:
            raise self._error(line_number, None, "one line per LF or CRLF line end (found a bare CR)")
        stripped = text.strip()
        if not stripped or stripped.startswith("#"):
            return None
        if self.header is None:
            self._read_header(stripped, line_number)
            return None
        body = stripped.split("#", 1)[0]
        tokens = body.split()
        if self._mask_tokens is None:
            self._read_mask(tokens, line_number)
            return None
        return self._read_values(tokens, line_number)

    def _read_header(self, text: str, line: int) -> None:
        tokens = text.split()
        if len(tokens) < 3:
            raise self._error(line, text if len(text) < 60 else None,
                              "a header line 'version name fps frame_count' (e.g. '2.1 speech 25 120')")
        version = tokens[0]
        if version not in SUPPORTED_VERSIONS:
            raise self._error(line, version, f"a .fap version ({', '.join(SUPPORTED_VERSIONS)})")
        fps = self._number(tokens[-2], line, "frames per second")
        if not MIN_FPS <= fps <= _MAX_FPS:  # 1e-300 played for ever and overflowed a glTF's key times
            raise self._error(line, tokens[-2], f"frames per second in [{MIN_FPS:g}, {_MAX_FPS:g}]")
        count = self._integer(tokens[-1], line, "the declared frame count", 0, _MAX_NUMBER)
        if len(tokens) == 3:
            name = ""
            self._warn_once("noname", f"line {line}: header has no name")
        else:
            # Keep the name's inner spacing as written.
            start = text.index(tokens[1], len(version))
            end = text.rindex(tokens[-2], 0, text.rindex(tokens[-1]))
            name = text[start:end].strip()
        if version == "2.0":
            self._warn_once("v2.0", f"line {line}: version 2.0: values are read in FAPU units like 2.1 "
                            "(no rescaling; some 2.0 writers may have scaled values differently)")
        self.header = FapHeader(version, name, fps, count)

    def _read_mask(self, tokens: list[str], line: int) -> None:
        for token in tokens:
            if token not in ("0", "1"):
                raise self._error(line, token, "a mask bit 0 or 1")
        if len(tokens) == FAP_COUNT + 1:
            if tokens[0] == "0":
                tokens = tokens[1:]
                self._warn_once("mask69", f"line {line}: 69-token masks; the leading (unused) slot is ignored")
            elif tokens[-1] == "0":
                tokens = tokens[:-1]
                self._warn_once("mask69", f"line {line}: 69-token masks; the trailing (unused) slot is ignored")
            else:
                raise self._error(line, tokens[0], "0 in the unused first or last slot of a 69-token mask")
        elif len(tokens) != FAP_COUNT:
            raise self._error(line, None, f"a mask line of {FAP_COUNT} (or 69) tokens 0/1, got {len(tokens)} tokens")
        self._mask_tokens = tokens
        self._mask_line = line

    def _read_values(self, tokens: list[str], line: int) -> FapFrame:
        mask = np.array([t == "1" for t in self._mask_tokens], dtype=bool)
        self._mask_tokens = None
        if not tokens:
            raise self._error(line, None, "a values line starting with the frame number")
        number = self._integer(tokens[0], line, "the frame number", 0, _MAX_NUMBER)
        if self._last_number is not None:
            if number <= self._last_number:
                raise self._error(line, tokens[0], f"a frame number greater than the previous one ({self._last_number})")
            if number > self._last_number + 1:
                self._warn_once("gap", f"line {line}: frame numbers skip from {self._last_number} to {number} "
                                "(values are held over missing frames)")
        values_tokens = tokens[1:]
        low_count = int(mask[2:].sum())
        forms1 = (1, _VISEME_TOKENS) if mask[0] else (0,)
        forms2 = (1, _EXPRESSION_TOKENS) if mask[1] else (0,)
        fits = [(a, b) for a in forms1 for b in forms2 if a + b + low_count == len(values_tokens)]
        if len(fits) != 1:
            want = sorted({a + b + low_count for a in forms1 for b in forms2})
            alternatives = " or ".join(str(n) for n in want)
            raise self._error(line, None, f"{alternatives} values after the frame number for the {int(mask.sum())} "
                              f"FAPs the mask on line {self._mask_line} selects, got {len(values_tokens)}")
        n1, n2 = fits[0]
        values = np.zeros(FAP_COUNT, dtype=np.float64)
        viseme = expression = None
        pos = 0
        if n1 == 1:
            values[0], viseme = self._single_highlevel(values_tokens[0], line, 1, VISEME_SELECT_MAX)
        elif n1 == _VISEME_TOKENS:
            t = values_tokens[:_VISEME_TOKENS]
            viseme = Viseme(self._integer(t[0], line, "viseme_select1", 0, VISEME_SELECT_MAX),
                            self._integer(t[1], line, "viseme_select2", 0, VISEME_SELECT_MAX),
                            self._integer(t[2], line, "viseme_blend", 0, BLEND_MAX),
                            self._integer(t[3], line, "viseme_def", 0, 1))
            values[0] = viseme.select1
        pos += n1
        if n2 == 1:
            values[1], expression = self._single_highlevel(values_tokens[pos], line, 2, EXPRESSION_SELECT_MAX)
        elif n2 == _EXPRESSION_TOKENS:
            t = values_tokens[pos:pos + _EXPRESSION_TOKENS]
            expression = Expression(self._integer(t[0], line, "expression_select1", 0, EXPRESSION_SELECT_MAX),
                                    self._integer(t[1], line, "expression_intensity1", 0, BLEND_MAX),
                                    self._integer(t[2], line, "expression_select2", 0, EXPRESSION_SELECT_MAX),
                                    self._integer(t[3], line, "expression_intensity2", 0, BLEND_MAX),
                                    self._integer(t[4], line, "init_face", 0, 1),
                                    self._integer(t[5], line, "expression_def", 0, 1))
            values[1] = expression.select1
        pos += n2
        low_index = np.flatnonzero(mask[2:]) + 2
        low_tokens = values_tokens[pos:]
        low = None
        if _NUMBER_CHARS.issuperset("".join(low_tokens)):  # fast path: one conversion
            try:
                low = np.array(low_tokens, dtype=np.float64)
            except ValueError:
                low = None
            if low is not None and not np.isfinite(low).all():
                low = None
        if low is None:  # find the offending token, for the error message
            low = np.array([self._number(t, line, f"a value for FAP {i + 1}") for i, t in zip(low_index, low_tokens)])
        values[low_index] = low
        self._last_number = number
        self.frame_count += 1
        return FapFrame(number, mask, values, viseme, expression)

    def _single_highlevel(self, token: str, line: int, fap: int, top: int):
        value = self._number(token, line, f"a value for FAP {fap}")
        if value.is_integer() and 0 <= value <= top:
            code = int(value)
            record = Viseme(code, 0, BLEND_MAX, 0) if fap == 1 else Expression(code, BLEND_MAX, 0, 0, 0, 0)
            return value, record
        kind = "viseme" if fap == 1 else "expression"
        self._warn_once(f"single{fap}", f"line {line}: FAP {fap} single token {token!r} is not a {kind} code 0..{top}; "
                        f"kept as a value, no {kind} shown")
        return value, None

    @property
    def in_frame(self) -> bool:
        """True between a frame's mask line and its values line."""
        return self._mask_tokens is not None

    def discard_partial_frame(self) -> bool:
        """Forget a mask line still waiting for its values line (e.g. the values line was
        lost: unreadable bytes, an overlong line). The next content line is read as a mask.

        Returns True when a pending mask was dropped, False when none was pending.
        """
        pending = self._mask_tokens is not None
        self._mask_tokens = None
        return pending

    def finish(self) -> None:
        """Call at the end of the stream: checks what only the end can tell (raises or warns)."""
        if self.header is None:
            raise self._error(0, None, "a header line 'version name fps frame_count' (the stream is empty)")
        if self._mask_tokens is not None:
            self._warn_once("trunc", f"line {self._mask_line}: mask line without a values line at the end; "
                            "that frame is dropped")
            self._mask_tokens = None
        if self.frame_count != self.header.declared_frame_count:
            self._warn_once("count", f"header declares {self.header.declared_frame_count} frames, "
                            f"the body has {self.frame_count}")


class FapStream:
    """A .fap file opened for streaming: the header now, frames as they are read.

    ``header`` is read when the stream is opened. Iterating reads the file from after the
    header, one line at a time (memory does not grow with the file), yielding
    :class:`FapFrame`; each iteration starts again from the first frame. ``warnings``
    holds the header's warnings and, as an iteration goes, the body's; ``frame_count`` is
    None until an iteration has reached the end.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.source_name = str(path)
        self.frame_count: int | None = None
        parser = FapParser(self.source_name)
        self._body_offset, self._body_line = self._scan_header(parser)
        self.header: FapHeader = parser.header
        self._header_warnings = list(parser.warnings)
        self._header_warned = parser.warned_keys
        self.warnings: list[str] = list(parser.warnings)

    def _open(self):
        try:
            return open(self.path, "rb")
        except (OSError, ValueError) as exc:
            reason = getattr(exc, "strerror", None) or str(exc)
            raise FapFormatError(self.source_name, 0, None, f"a readable .fap file ({reason})") from None

    def _lines(self, handle, parser: FapParser, first_line: int) -> Iterator[tuple[str, int]]:
        number = first_line
        warned = False
        while True:
            try:
                raw = handle.readline(MAX_LINE_BYTES + 1)
            except OSError as exc:
                raise FapFormatError(self.source_name, number, None, f"a readable file ({exc})") from None
            if not raw:
                return
            if len(raw) > MAX_LINE_BYTES and not raw.endswith(b"\n"):
                raise FapFormatError(self.source_name, number, None, f"lines shorter than {MAX_LINE_BYTES} bytes")
            text, utf8 = _decode(raw)
            if not utf8 and not warned:
                warned = True
                parser.warn_once("latin1", f"line {number}: not UTF-8; read as Latin-1")
            yield text, number
            number += 1

    def _scan_header(self, parser: FapParser) -> tuple[int, int]:
        with self._open() as handle:
            line_number = 1
            for text, line_number in self._lines(handle, parser, 1):
                parser.feed_line(text, line_number)
                if parser.header is not None:
                    return handle.tell(), line_number + 1
            parser.finish()  # raises: no header
        raise AssertionError("unreachable")  # pragma: no cover

    def __iter__(self) -> Iterator[FapFrame]:
        self.warnings = list(self._header_warnings)
        parser = FapParser.after_header(self.source_name, self.header, self._header_warned, self.warnings)
        with self._open() as handle:
            handle.seek(self._body_offset)
            for text, line_number in self._lines(handle, parser, self._body_line):
                frame = parser.feed_line(text, line_number)
                if frame is not None:
                    yield frame
        parser.finish()
        self.frame_count = parser.frame_count


def read_fap(path: str | os.PathLike) -> FapStream:
    """Open a .fap file: ``read_fap(p).header`` at once, ``for frame in read_fap(p)`` streams.

    Raises :class:`FapFormatError` (never another exception) for a missing or unreadable
    file or one that fae cannot understand.
    """
    return FapStream(path)


# -- writing ---------------------------------------------------------------------
def _format_value(value: float) -> str:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"cannot write a non-finite FAP value {value!r}")
    if value.is_integer():
        return str(int(value))
    return repr(value)


def format_header(header: FapHeader, frame_count: int | None = None) -> str:
    """The header line (no line end) of a v2.1 stream; `frame_count` overrides the declared count."""
    name = " ".join(header.name.split()) or "fae"
    count = header.declared_frame_count if frame_count is None else frame_count
    return f"{WRITE_VERSION} {name} {_format_value(header.fps)} {int(count)}"


def format_frame(frame: FapFrame) -> str:
    """The mask line and values line (joined by a newline, no final line end) of one frame."""
    mask = np.asarray(frame.mask, dtype=bool)
    values = np.asarray(frame.values, dtype=np.float64)
    if mask.shape != (FAP_COUNT,) or values.shape != (FAP_COUNT,):
        raise ValueError(f"frame {frame.number}: mask and values must have shape ({FAP_COUNT},)")
    out = [str(int(frame.number))]
    if mask[0]:
        v = frame.viseme
        out += [str(v.select1), str(v.select2), str(v.blend), str(v.definition)] if v else [_format_value(values[0])]
    if mask[1]:
        e = frame.expression
        out += ([str(e.select1), str(e.intensity1), str(e.select2), str(e.intensity2), str(e.init_face),
                 str(e.definition)] if e else [_format_value(values[1])])
    out += [_format_value(values[i]) for i in np.flatnonzero(mask[2:]) + 2]
    return " ".join("1" if m else "0" for m in mask) + "\n" + " ".join(out)


def write_fap(path: str | os.PathLike, header: FapHeader, frames: Iterable[FapFrame]) -> int:
    """Write a v2.1 .fap file atomically (the file appears only when complete).

    header  its name and fps are written; the declared frame count is the number of
            frames written. Integer values are written as integers, others with full
            float precision, so reading the file back gives the same frames.
    Returns the number of frames written.
    """
    lines = [format_frame(frame) for frame in frames]
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="\n") as out:
            out.write(format_header(header, len(lines)) + "\n")
            for text in lines:
                out.write(text + "\n")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # an ordinary file, as open() would have made it
    return len(lines)
