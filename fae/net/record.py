"""Record what the server plays into an mp4 that keeps the performance's time.

The recorder is a lossless subscriber: a stream that outruns rendering waits for it. It
follows one stream at a time (the first one it sees; when that stream ends, the next one
that plays), so concurrent clients never interleave in the video; frames of streams it is
not following are counted in `skipped`. Rendering runs in one thread of its own (an
OpenGL context belongs to the thread that made it). The file appears only when the
recorder is closed cleanly.

Time: each pose is held in the video until the next one arrives (RecordingClock says
when). A native stream's frames fall at their own times (frame number / the stream's
fps), so coalesced frames repeat their step's image and the video lasts as long as the
stream. Xface frames fall when they were played, by the wall clock: a client that
uploads the latest pose once a second gets a video in which each pose lasts a second.
A pose that falls in the same video frame as the next one is not shown. No pose of a
native stream is held longer than MAX_HOLD_SECONDS (`fae play`'s default --max-hold): a
longer gap between its frame numbers (0 then 10^12, which the protocol allows) is cut to
it, and counted in `gaps_cut`; an Xface pause lasts as long as it did live.
"""

from __future__ import annotations

import asyncio
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from fae.io.frames import MAX_HOLD_SECONDS
from fae.net.faces import Pose
from fae.net.hub import FrameEvent, StreamEnd, Subscription
from fae.net.stage import STREAM as XFACE_STREAM


class FrameRenderer(Protocol):
    def render(self, skin_vertices: np.ndarray, bone_transforms: dict, pupil_scale: dict) -> np.ndarray:
        """(H, W, 3) uint8 RGB image of the pose (fae.render.renderer.FaceRenderer.render)."""

    def close(self) -> None: ...


class RecordingClock:
    """Seconds on the video's timeline at which each recorded frame starts to show.

    period  one video frame (s): a stream that follows another one starts one frame after
            the previous stream's last pose

    A native stream keeps its own clock (FrameEvent.time); Xface frames keep the wall
    clock (FrameEvent.made), across uploads too, so the pauses between uploads last as long
    in the video as they did live. Times never go backwards.
    """

    def __init__(self, period: float) -> None:
        self.period = period
        self.last: float | None = None
        self._anchor: tuple[bool, float, float] | None = None  # (wall clock?, video s, source s)

    def place(self, event: FrameEvent, starts_stream: bool) -> float:
        """The video time of `event`; `starts_stream`: the first frame of a stream followed."""
        live = event.stream == XFACE_STREAM
        source = event.made if live else event.time
        if self._anchor is None or (starts_stream and not (live and self._anchor[0])):
            start = 0.0 if self.last is None else self.last + self.period
            self._anchor = (live, start, source)
        _, video, origin = self._anchor
        t = video + (source - origin)
        self.last = t if self.last is None else max(t, self.last)
        return self.last


class StreamRecorder:
    """Render the frames of a subscription into `path` (an .mp4).

    subscription      a lossless subscription (FapServer.subscribe(lossless=True))
    renderer_factory  builds the renderer, in the recording thread
    size              (width, height) pixels, even
    fps               video frame rate; None: the first recorded stream's own

    frames_written    video frames so far; frames_rendered: poses rendered for them;
    skipped           frames of streams played while another one was being recorded
    gaps_cut          holds cut to MAX_HOLD_SECONDS
    """

    def __init__(self, subscription: Subscription, path: str | Path, renderer_factory: Callable[[], FrameRenderer],
                 size: tuple[int, int], fps: float | None = None) -> None:
        if not subscription.lossless:
            raise ValueError("StreamRecorder: expected a lossless subscription (every frame must be recorded)")
        self.subscription = subscription
        self.path = Path(path)
        self.renderer_factory = renderer_factory
        self.size = size
        self.fps = fps
        self.frames_written = 0
        self.frames_rendered = 0
        self.skipped = 0
        self.gaps_cut = 0
        self._cut = 0  # video frames the cut gaps took out of the clock's time
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fae-record")
        self._renderer: FrameRenderer | None = None
        self._writer = None
        self._task: asyncio.Task | None = None
        self._clock: RecordingClock | None = None
        self._held: Pose | None = None  # the latest pose, shown until the next one's time
        self._last_pose: Pose | None = None
        self._last_image: np.ndarray | None = None

    def start(self) -> None:
        self._task = asyncio.create_task(self._run())

    def _show(self, pose: Pose, count: int) -> None:
        """Write `count` video frames of `pose` (rendered once however often it is written)."""
        from fae.render.video import VideoWriter

        if self._renderer is None:
            self._renderer = self.renderer_factory()
        if self._writer is None:
            self._writer = VideoWriter(self.path, self.size, self.fps)
        if pose is not self._last_pose:
            self._last_image = self._renderer.render(pose.skin_vertices, pose.bone_transforms, pose.pupil_scale)
            self._last_pose = pose
            self.frames_rendered += 1
        for _ in range(count):
            self._writer.write(self._last_image)
            self.frames_written += 1

    def _finish(self, ok: bool) -> None:
        try:
            if ok and self._held is not None:  # the last pose: shown for one frame
                self._show(self._held, 1)
                self._held = None
        except BaseException:
            ok = False
            raise
        finally:
            try:
                if self._writer is not None:
                    self._writer.close() if ok else self._writer.abort()
            finally:
                if self._renderer is not None:
                    self._renderer.close()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        following: str | None = None
        async for event in self.subscription:
            if isinstance(event, StreamEnd):
                if event.stream == following:
                    following = None
                continue
            starts_stream = following is None
            if starts_stream:
                following = event.stream
            if event.stream != following:
                self.skipped += 1
                continue
            if self._clock is None:
                self.fps = self.fps or event.fps
                self._clock = RecordingClock(1.0 / self.fps)
            slot = math.floor(self._clock.place(event, starts_stream) * self.fps + 0.5) - self._cut
            held, self._held = self._held, event.pose
            gap = slot - self.frames_written
            longest = max(1, math.ceil(MAX_HOLD_SECONDS * self.fps))
            if gap > longest and event.stream != XFACE_STREAM:
                self._cut += gap - longest
                self.gaps_cut += 1
                gap = longest
            if held is not None and gap > 0:  # hold the previous pose until now
                await loop.run_in_executor(self._executor, self._show, held, gap)

    async def close(self, ok: bool = True) -> None:
        """After the server has closed (its subscriptions ended): finish the file.

        ok=False discards it. Raises what rendering or encoding raised.
        """
        failure = None
        if self._task is not None:
            if not ok:
                self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            except Exception as exc:  # keep the file out, report the cause
                failure, ok = exc, False
        loop = asyncio.get_running_loop()
        try:
            await loop.run_in_executor(self._executor, self._finish, ok)
        finally:
            self._executor.shutdown(wait=True)
        if failure is not None:
            raise failure
