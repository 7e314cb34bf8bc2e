"""Bounded line framing for the native protocol: bytes in, numbered text lines out."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Line:
    """One received line.

    number    1-based line number in the connection's stream
    text      the line without its end (LF or CRLF), or None when it could not be used
    problem   why `text` is None: the line was longer than the limit or not UTF-8
    """

    number: int
    text: str | None
    problem: str | None = None


class LineSplitter:
    """Cut a byte stream into lines of at most `max_line` bytes.

    An overlong line is reported once (as soon as the limit is passed) and its remaining
    bytes are discarded up to the next newline, so a client that never sends a newline
    costs at most `max_line` bytes of memory.
    """

    def __init__(self, max_line: int = 8192) -> None:
        self.max_line = int(max_line)
        self._buf = bytearray()
        self._discarding = False
        self._count = 0

    @property
    def line_count(self) -> int:
        """Lines reported so far."""
        return self._count

    @property
    def pending(self) -> bool:
        """True while part of a line is buffered (a frame cut off by a disconnect)."""
        return bool(self._buf) and not self._discarding

    def feed(self, data: bytes) -> list[Line]:
        """Add bytes; return the complete lines now available, in order."""
        out: list[Line] = []
        view = memoryview(data)
        pos = 0
        while pos < len(view):
            nl = data.find(b"\n", pos)
            if self._discarding:
                if nl < 0:
                    return out
                self._discarding = False
                pos = nl + 1
                continue
            if nl < 0:
                self._buf += view[pos:]
                if len(self._buf) > self.max_line:
                    self._buf.clear()
                    self._discarding = True
                    out.append(self._overlong())
                return out
            self._buf += view[pos:nl]
            pos = nl + 1
            raw = bytes(self._buf)
            self._buf.clear()
            if len(raw) > self.max_line:
                out.append(self._overlong())
                continue
            out.append(self._decode(raw))
        return out

    def _overlong(self) -> Line:
        self._count += 1
        return Line(self._count, None, f"expected a line of at most {self.max_line} bytes")

    def _decode(self, raw: bytes) -> Line:
        self._count += 1
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            return Line(self._count, None, f"byte {exc.start}: expected UTF-8 text")
        if "\0" in text:
            return Line(self._count, None, f"byte {text.index(chr(0))}: expected text, got a NUL byte")
        return Line(self._count, text)
