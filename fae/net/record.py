"""Record what the server plays into an mp4, one whole stream after another.

The recorder is a lossless subscriber: a stream that outruns rendering waits for it, so
every frame of a recorded stream is in the video. It follows one stream at a time (the
first one it sees; when that stream ends, the next one that plays), so concurrent
clients never interleave in the video; frames of streams it is not following are counted
in `skipped`. Rendering runs in one thread of its own (an OpenGL context belongs to the
thread that made it). Frames that share one pose (the face coalesced them into one step)
are rendered once and written as many times, so the video keeps the stream's timing.
The file appears only when the recorder is closed cleanly.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from fae.net.hub import FrameEvent, StreamEnd, Subscription


class FrameRenderer(Protocol):
    def render(self, skin_vertices: np.ndarray, bone_transforms: dict, pupil_scale: dict) -> np.ndarray:
        """(H, W, 3) uint8 RGB image of the pose (fae.render.renderer.FaceRenderer.render)."""

    def close(self) -> None: ...


class StreamRecorder:
    """Render the frames of a subscription into `path` (an .mp4).

    subscription      a lossless subscription (FapServer.subscribe(lossless=True))
    renderer_factory  builds the renderer, in the recording thread
    size              (width, height) pixels, even
    fps               video frame rate; None: the first recorded stream's own
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
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fae-record")
        self._renderer: FrameRenderer | None = None
        self._writer = None
        self._task: asyncio.Task | None = None
        self._last_pose = None
        self._last_image: np.ndarray | None = None

    def start(self) -> None:
        self._task = asyncio.create_task(self._run())

    def _write(self, event: FrameEvent) -> None:
        from fae.render.video import VideoWriter

        if self._renderer is None:
            self._renderer = self.renderer_factory()
        if self._writer is None:
            self._writer = VideoWriter(self.path, self.size, self.fps or event.fps)
        if event.pose is not self._last_pose:
            pose = event.pose
            self._last_image = self._renderer.render(pose.skin_vertices, pose.bone_transforms, pose.pupil_scale)
            self._last_pose = pose
            self.frames_rendered += 1
        self._writer.write(self._last_image)
        self.frames_written += 1

    def _finish(self, ok: bool) -> None:
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
            if following is None:
                following = event.stream
            if event.stream != following:
                self.skipped += 1
                continue
            await loop.run_in_executor(self._executor, self._write, event)

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
        await loop.run_in_executor(self._executor, self._finish, ok)
        self._executor.shutdown(wait=True)
        if failure is not None:
            raise failure
