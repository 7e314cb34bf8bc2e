"""Frame semantics: sparse .fap frames -> dense per-frame FAP values, in one place.

Rules (ISO/IEC 14496-2 FBA masking; the .fap text format carries no per-group mask type,
so fae applies the standard's "bit mask follows" semantics):

- hold: a FAP not sent in a frame keeps its last value (0, the neutral face, until first
  sent). The viseme and expression records are held the same way.
- fill (``fill=True``, off by default): the standard lets a decoder interpolate unsent FAPs
  of a group whose mask type allows it (FIT or symmetry). fae's default FIT: a FAP not sent
  in a frame whose left/right partner was sent takes the partner's value (the standard
  defines left/right pairs so that equal values are mirror-symmetric); failing that, an
  inner lip FAP takes its outer lip partner's value and vice versa (same FAPU, same
  direction); failing that, it holds.
- clamp (``clamp=True``): values outside the standard's range are clamped. The range used
  is the I (intra) range times the quantiser step
  (:attr:`fae.mpeg4.faps.FapInfo.value_range`): an intra frame codes the value itself, so
  its range bounds values; the P range bounds frame-to-frame differences and would clamp
  legitimate poses (e.g. a head turn of 8500 AU is within 1860 x 170 but a P range reading
  of 600 would cut it). FAPs 1 and 2 (codes) are not clamped. The face plays a narrower
  range still (fae.mpeg4.faptables.FAP_LIMITS, e.g. open_jaw 0..1080 MNS): one warning
  per FAP names that range, the one a viewer sees the value cut to (a unidirectional FAP
  slightly below 0, as real streams send, is cut to 0 without a warning).
- time: the first frame of a stream is at t = 0 whatever its number (0 or 1); frame
  numbers that skip are filled with held frames so dense index k is at t = k / fps.
- long gaps: a hold is cut to ``max_hold`` seconds (MAX_HOLD_SECONDS by default; None: no
  limit), with one warning per cut, and the frames after it come that much earlier. A
  stream of frames 0 and 10**12 is legal, but playing its 1.3 years of held frames is not
  what anyone asked for; the cut keeps the cost of any gap bounded.
- resampling to another fps: output frame j is at t = j / fps_out for all t inside the
  stream's duration N / fps_in (so there are ceil(N * fps_out / fps_in) frames); values
  are interpolated linearly between the two source frames around t, the viseme and
  expression come from the nearest earlier source frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from fae.mpeg4.faptables import FAP_LIMITS
from fae.io.fap import FapFrame
from fae.mpeg4.faps import FAP_COUNT, FAPS, LIP_PARTNER_FAP, MIRROR_FAP
from fae.mpeg4.highlevel import Expression, Viseme

__all__ = ["DenseFrame", "FrameState", "DenseFrames", "dense_frames", "MAX_HOLD_SECONDS"]

MAX_HOLD_SECONDS = 60.0  # longest hold played by default (a pause in speech is seconds)


@dataclass(eq=False)
class DenseFrame:
    """The full FAP state at one output frame.

    index       0-based output frame index
    time        seconds from the stream's first frame (index / fps)
    values      (68,) float64, FAP number-1, FAPU / AU units; every FAP has a value
    viseme      the current FAP 1 record (held), or None
    expression  the current FAP 2 record (held), or None
    """

    index: int
    time: float
    values: np.ndarray
    viseme: Viseme | None = None
    expression: Expression | None = None


def _partner_index(pairs: dict[int, int]) -> np.ndarray:
    index = np.full(FAP_COUNT, -1, dtype=np.int64)
    for number, partner in pairs.items():
        index[number - 1] = partner - 1
    return index


_MIRROR_INDEX = _partner_index(MIRROR_FAP)
_LIP_INDEX = _partner_index(LIP_PARTNER_FAP)
_RANGE_LOW = np.array([-np.inf if i < 2 else FAPS[i].value_range[0] for i in range(FAP_COUNT)])
_RANGE_HIGH = np.array([np.inf if i < 2 else FAPS[i].value_range[1] for i in range(FAP_COUNT)])
# Values beyond these get the clamp warning. A unidirectional FAP (open_jaw, lift_*_cheek, ...)
# is played from 0 up, but real streams send it slightly negative (-4 in the Xface samples):
# that cut is the FAP's definition, not news, so only a value as far below 0 as its top
# is above is warned about.
WARN_HIGH = np.where(np.arange(FAP_COUNT) < 2, np.inf, FAP_LIMITS[:, 1])
WARN_LOW = np.where(np.arange(FAP_COUNT) < 2, -np.inf,
                    np.where(FAP_LIMITS[:, 0] >= 0, -FAP_LIMITS[:, 1], FAP_LIMITS[:, 0]))


class FrameState:
    """Folds frames into the current dense FAP state, one frame at a time (the player and
    the socket server feed it as frames arrive).

    ``update(frame)`` returns the (68,) float64 values after `frame`; ``viseme`` and
    ``expression`` are the held high-level records; ``warnings`` collects one clamp warning
    per FAP.
    """

    def __init__(self, fill: bool = False, clamp: bool = True, source_name: str = "<stream>"):
        self.fill = bool(fill)
        self.clamp = bool(clamp)
        self.source_name = source_name
        self.values = np.zeros(FAP_COUNT, dtype=np.float64)
        self.viseme: Viseme | None = None
        self.expression: Expression | None = None
        self.warnings: list[str] = []
        self._clamped = np.zeros(FAP_COUNT, dtype=bool)

    def update(self, frame: FapFrame) -> np.ndarray:
        """Apply one frame; returns a copy of the new (68,) values."""
        sent = np.asarray(frame.mask, dtype=bool)
        incoming = np.asarray(frame.values, dtype=np.float64)
        values = np.where(sent, incoming, self.values)
        if self.fill:
            has_mirror = _MIRROR_INDEX >= 0
            from_mirror = ~sent & has_mirror & sent[np.where(has_mirror, _MIRROR_INDEX, 0)]
            values[from_mirror] = incoming[_MIRROR_INDEX[from_mirror]]
            has_lip = _LIP_INDEX >= 0
            from_lip = ~sent & ~from_mirror & has_lip & sent[np.where(has_lip, _LIP_INDEX, 0)]
            values[from_lip] = incoming[_LIP_INDEX[from_lip]]
        if self.clamp:
            outside = (values < WARN_LOW) | (values > WARN_HIGH)
            if outside.any():
                for i in np.flatnonzero(outside & ~self._clamped):
                    info = FAPS[i]
                    low, high = FAP_LIMITS[i]
                    self.warnings.append(
                        f"{self.source_name}: frame {frame.number}: FAP {info.number} {info.name} = {values[i]:g} "
                        f"{info.fapu} is outside [{low:g}, {high:g}], the range the face plays; played as "
                        f"{min(max(values[i], low), high):g} here and cut to that range wherever else it is outside")
                self._clamped |= outside
                values = np.clip(values, _RANGE_LOW, _RANGE_HIGH)
        if sent[0]:
            self.viseme = frame.viseme
        if sent[1]:
            self.expression = frame.expression
        self.values = values
        return values.copy()


class DenseFrames:
    """Iterable of :class:`DenseFrame` built from a frame stream (see :func:`dense_frames`).

    Each ``for`` loop starts again from the first frame (when the source can be iterated
    again, as a :class:`fae.io.fap.FapStream` can); ``next()`` walks one shared pass.
    ``warnings`` collects the clamp warnings of the latest pass.
    """

    def __init__(self, frames: Iterable[FapFrame], source_fps: float, fps: float | None, fill: bool,
                 clamp: bool, source_name: str, max_hold: float | None = MAX_HOLD_SECONDS):
        if not (math.isfinite(source_fps) and source_fps > 0):
            raise ValueError(f"{source_name}: source fps must be positive, got {source_fps!r}")
        if max_hold is not None and not max_hold >= 0:
            raise ValueError(f"max_hold must be a number of seconds >= 0 or None, got {max_hold!r}")
        self.max_hold = max_hold
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"output fps must be positive, got {fps!r}")
        self.frames = frames
        self.source_fps = float(source_fps)
        self.fps = float(fps) if fps is not None else self.source_fps
        self.fill = fill
        self.clamp = clamp
        self.source_name = source_name
        self.warnings: list[str] = []
        self._pass: Iterator[DenseFrame] | None = None

    def __next__(self) -> DenseFrame:
        if self._pass is None:
            self._pass = iter(self)
        return next(self._pass)

    def _indexed(self) -> Iterator[tuple[FapFrame, int, int | None]]:
        """(frame, its index in the source's dense timeline, the frame number before it when
        the gap between them was cut to max_hold, else None), a frame at a time."""
        first = None
        previous_index = previous_number = None
        cut = 0  # frames left out of long holds so far
        longest = None if self.max_hold is None else math.floor(self.max_hold * self.source_fps + 1e-9)
        for frame in self.frames:
            if first is None:
                first = frame.number
            index = frame.number - first - cut
            held_from = None
            if previous_index is not None and longest is not None and index - previous_index - 1 > longest:
                held_from = previous_number
                cut += index - previous_index - 1 - longest
                index = previous_index + 1 + longest
            yield frame, index, held_from
            previous_index, previous_number = index, frame.number

    def count(self) -> int:
        """The number of frames a pass yields, from the source's frame numbers alone (held
        frames are not made: a gap of millions of frames is counted at once). It is a pass
        over the source: a one-shot iterator of frames is used up; frame numbers are taken to
        rise, as read_fap ensures."""
        last = -1
        for _, index, _ in self._indexed():
            last = index
        if self.fps == self.source_fps:
            return last + 1
        return math.ceil((last + 1) * self.fps / self.source_fps - 1e-9) if last >= 0 else 0

    def _source(self, state: FrameState) -> Iterator[DenseFrame]:
        previous: DenseFrame | None = None
        for frame, index, held_from in self._indexed():
            if held_from is not None:
                missing = frame.number - held_from - 1
                state.warnings.append(
                    f"{self.source_name}: frames {held_from + 1}..{frame.number - 1} are missing "
                    f"({missing / self.source_fps:.6g} s): frame {held_from} is held for {self.max_hold:g} s "
                    "only, and the stream goes on from there")
            if previous is not None:
                for held in range(previous.index + 1, index):  # frame numbers that skip: hold
                    yield DenseFrame(held, held / self.source_fps, previous.values.copy(), previous.viseme, previous.expression)
            values = state.update(frame)
            previous = DenseFrame(index, index / self.source_fps, values, state.viseme, state.expression)
            yield previous

    def __iter__(self) -> Iterator[DenseFrame]:
        state = FrameState(self.fill, self.clamp, self.source_name)
        self.warnings = state.warnings
        source = self._source(state)
        if self.fps == self.source_fps:
            yield from source
            return
        ratio = self.source_fps / self.fps  # source frames per output frame
        j = 0
        before: DenseFrame | None = None
        count = 0
        for after in source:
            count += 1
            if before is not None:
                # Output frames whose source position lies in [before.index, after.index).
                while True:
                    position = j * ratio
                    k = math.floor(position + 1e-9)
                    if k >= after.index:
                        break
                    a = min(max(position - k, 0.0), 1.0)
                    values = before.values + a * (after.values - before.values)
                    yield DenseFrame(j, j / self.fps, values, before.viseme, before.expression)
                    j += 1
            before = after
        if before is None:
            return
        total = math.ceil(count * self.fps / self.source_fps - 1e-9)
        while j < total:
            yield DenseFrame(j, j / self.fps, before.values.copy(), before.viseme, before.expression)
            j += 1


def dense_frames(stream, fps: float | None = None, fill: bool = False, clamp: bool = True,
                 source_fps: float | None = None, max_hold: float | None = MAX_HOLD_SECONDS) -> DenseFrames:
    """Dense frames of a stream: every FAP valued at every frame (see the module rules).

    stream      a :class:`fae.io.fap.FapStream` (its header gives the fps) or any iterable
                of :class:`FapFrame` together with `source_fps`
    fps         output frame rate (None: the stream's own)
    fill        fill unsent FAPs from their left/right, then inner/outer lip partner
    clamp       clamp to the standard's value ranges (one warning per FAP)
    max_hold    seconds a gap in the frame numbers is held at most (None: as long as it is)
    Returns a re-iterable :class:`DenseFrames` whose ``warnings`` lists the clamp and cut
    warnings.
    """
    header = getattr(stream, "header", None)
    if source_fps is None:
        if header is None:
            raise ValueError("dense_frames: give source_fps for a stream without a header")
        source_fps = header.fps
    name = getattr(stream, "source_name", "<stream>")
    return DenseFrames(stream, source_fps, fps, fill, clamp, name, max_hold)
