"""One .fap stream arriving line by line: header, then mask/values pairs -> dense frames.

Wraps the incremental reader (fae.io.fap) and the hold/clamp state (fae.io.frames) for
the server: a bad frame is reported and skipped, and the stream goes on with the next
frame (the reader is re-synchronized on the next mask line).
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass

from fae.io.fap import FapFormatError, FapParser
from fae.mpeg4.faps import FAP_COUNT
from fae.io.frames import DenseFrame, FrameState

__all__ = ["FapFormatError", "HeaderRead", "StreamFrame", "StreamDecoder", "HeldFrames", "decode_text"]


@dataclass(frozen=True)
class HeaderRead:
    """The stream's header line was accepted; fps is its frame rate (frames/s)."""

    fps: float
    frame_count: int


@dataclass(frozen=True)
class StreamFrame:
    """One decoded frame of a live stream.

    number  the frame number as the client wrote it (acknowledged as `ok <number>`)
    dt      seconds since the previous frame (frame-number gap / fps; 1 / fps first)
    dense   the held, clamped FAP state (index counts from the stream's first frame)
    """

    number: int
    dt: float
    dense: DenseFrame


class StreamDecoder:
    """Feed text lines; get HeaderRead once, then a StreamFrame per complete frame.

    After a bad mask line the next line is taken as that frame's values line and skipped
    unless it is itself a well-formed mask, so one bad frame gives one error.
    """

    def __init__(self, source_name: str) -> None:
        self.source_name = source_name
        self._parser = FapParser(source_name)
        self._state: FrameState | None = None
        self._skip_values = False
        self._first_number: int | None = None
        self._last_index = -1

    @property
    def header(self):
        """The FapHeader once read, else None."""
        return self._parser.header

    @property
    def fps(self) -> float:
        """Frames per second from the header (0 before it)."""
        return float(self.header.fps) if self.header is not None else 0.0

    @property
    def dt(self) -> float:
        """Seconds per frame."""
        return 1.0 / self.fps

    @property
    def in_frame(self) -> bool:
        """True between a frame's mask line and its values line."""
        return self._parser.in_frame

    def skip_line(self, number: int) -> None:
        """A line that could not be read at all (not text, too long): its frame is lost.

        If it came after a mask line it was that frame's values line: the pending mask is
        dropped. Otherwise it was (or cut) a mask line: the next line is taken as its values
        line and skipped unless it is itself a well-formed mask.
        """
        if self.header is None:
            return
        if not self._parser.discard_partial_frame():
            self._skip_values = True

    def feed(self, text: str, number: int):
        """Returns HeaderRead, a StreamFrame, or None (line consumed, frame incomplete).

        Raises FapFormatError; the frame it belongs to is dropped and the stream goes on.
        """
        stripped = text.strip()
        content = bool(stripped) and not stripped.startswith("#")
        if self.header is None:
            self._parser.feed_line(text, number)
            if self.header is None:
                return None
            self._state = FrameState(source_name=self.source_name)
            return HeaderRead(self.fps, int(self.header.declared_frame_count))
        if not content:
            return None
        if self._skip_values:
            self._skip_values = False
            tokens = stripped.split("#", 1)[0].split()
            if not (len(tokens) in (FAP_COUNT, FAP_COUNT + 1) and all(t in ("0", "1") for t in tokens)):
                return None
        was_mask = not self._parser.in_frame
        try:
            frame = self._parser.feed_line(text, number)
        except FapFormatError:
            if was_mask:
                self._skip_values = True
            raise
        if frame is None:
            return None
        values = self._state.update(frame)
        if self._first_number is None:
            self._first_number = frame.number
        index = frame.number - self._first_number
        dt = (index - self._last_index) / self.fps if self._last_index >= 0 else 1.0 / self.fps
        self._last_index = index
        dense = DenseFrame(index, index / self.fps, values, self._state.viseme, self._state.expression)
        return StreamFrame(frame.number, dt, dense)


class HeldFrames(Sequence):
    """A stream's dense frames, one per frame number from its first to its last, holding
    only the frames it sent: the frames of a gap are made when asked for, from the frame
    before the gap (their values are that frame's, shared, not copied). So a stream of two
    frames numbered 0 and 10**12 costs two frames of memory, not a trillion.

    keys  the dense frames the stream sent, their indices increasing (the first is 0)
    fps   the stream's frame rate (a frame's time is its index / fps)
    """

    def __init__(self, keys: list[DenseFrame], fps: float) -> None:
        self._keys = keys
        self._indices = [k.index for k in keys]
        self.fps = float(fps)

    @property
    def sent(self) -> int:
        """Frames the stream sent (the others hold one of them)."""
        return len(self._keys)

    def __len__(self) -> int:
        return self._indices[-1] + 1 if self._keys else 0

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i}: the stream has frames 0..{n - 1}")
        key = self._keys[bisect_right(self._indices, i) - 1]
        if key.index == i:
            return key
        return DenseFrame(i, i / self.fps, key.values, key.viseme, key.expression)


def decode_text(text: str, source_name: str) -> tuple[float, HeldFrames]:
    """A whole .fap text -> (fps, its dense frames: held, clamped, gaps held; see HeldFrames).
    Raises FapFormatError."""
    parser = FapParser(source_name)
    state = FrameState(source_name=source_name)
    keys: list[DenseFrame] = []
    first = None
    for number, line in enumerate(text.splitlines(), start=1):
        frame = parser.feed_line(line, number)
        if frame is not None:
            first = frame.number if first is None else first
            index = frame.number - first
            values = state.update(frame)
            keys.append(DenseFrame(index, index / parser.header.fps, values, state.viseme, state.expression))
    parser.finish()
    return float(parser.header.fps), HeldFrames(keys, parser.header.fps)
