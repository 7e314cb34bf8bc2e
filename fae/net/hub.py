"""Frames out of the server: subscriptions to every pose the server produces.

A viewer, a recorder or a test subscribes and reads :class:`FrameEvent` objects (and a
:class:`StreamEnd` when a stream finishes) from its own bounded queue. A lossy
subscription drops its oldest event when full, so a slow viewer never slows the
server; a lossless one (a recorder) makes the producing stream wait for room instead.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import AsyncIterator, Union

from fae.net.faces import Pose


@dataclass(frozen=True)
class FrameEvent:
    """One frame played on one stream.

    stream  the stream's name: "native-<client id>" or "xface"
    index   the frame number as the stream numbered it
    time    seconds on the stream's own clock (index / fps for .fap streams)
    fps     the stream's frame rate
    pose    the face's Pose after this frame
    step    the face's simulation step that produced `pose` (1, 2, ...): frames that
            arrived while the face was busy share one step, and one Pose object
    made    time.monotonic() when the event was made: when the pose was shown live
    """

    stream: str
    index: int
    time: float
    fps: float
    pose: Pose
    step: int = 0
    made: float = field(default_factory=time.monotonic)


@dataclass(frozen=True)
class StreamEnd:
    """A stream finished (its client left, or an Xface playback stopped or ended)."""

    stream: str


Event = Union[FrameEvent, StreamEnd]


class Subscription:
    """A bounded queue of events for one subscriber (use via FrameHub.subscribe).

    dropped  events discarded because this (lossy) subscriber fell behind
    """

    def __init__(self, hub: "FrameHub", maxsize: int, lossless: bool) -> None:
        if maxsize < 1:
            raise ValueError(f"subscription maxsize: expected >= 1, got {maxsize}")
        self._hub = hub
        self._queue: asyncio.Queue = asyncio.Queue(maxsize)
        self.lossless = lossless
        self.dropped = 0
        self.closed = False

    async def get(self) -> Event | None:
        """The next event, or None once the subscription or the server is closed."""
        if self.closed and self._queue.empty():
            return None
        item = await self._queue.get()
        if item is None:
            self.closed = True
        return item

    async def __aiter__(self) -> AsyncIterator[Event]:
        while (item := await self.get()) is not None:
            yield item

    def close(self) -> None:
        """Stop receiving; a pending or later get() returns None."""
        self._hub._remove(self)
        self._push_nowait(None)

    def _push_nowait(self, item: Event | None) -> None:
        while True:
            try:
                self._queue.put_nowait(item)
                return
            except asyncio.QueueFull:
                self._queue.get_nowait()
                if item is not None:
                    self.dropped += 1

    async def _push(self, item: Event) -> None:
        if self.lossless:
            await self._queue.put(item)
        else:
            self._push_nowait(item)


class FrameHub:
    """Fan-out of events to subscriptions, in publication order."""

    def __init__(self) -> None:
        self._subs: list[Subscription] = []

    def subscribe(self, maxsize: int = 8, lossless: bool = False) -> Subscription:
        """A new subscription. Lossy (default): drop-oldest. Lossless: producers wait."""
        sub = Subscription(self, maxsize, lossless)
        self._subs.append(sub)
        return sub

    @property
    def subscriber_count(self) -> int:
        return len(self._subs)

    async def publish(self, event: Event) -> None:
        """Deliver to every subscriber; waits only for lossless subscribers' room."""
        for sub in list(self._subs):
            await sub._push(event)

    async def close(self) -> None:
        """End every subscription (their get() returns None after queued events).

        A lossless subscriber keeps every queued event: this waits until it has room
        for the end marker.
        """
        for sub in list(self._subs):
            self._remove(sub)
            if sub.lossless:
                await sub._queue.put(None)
            else:
                sub._push_nowait(None)

    def _remove(self, sub: Subscription) -> None:
        if sub in self._subs:
            self._subs.remove(sub)
