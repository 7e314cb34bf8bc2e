"""The Xface side of the server: one shared face, one current stream, one task queue.

As in the Xface player, every Xface client drives the same face: tasks from all of
them go through one queue, in arrival order; a RESUME plays the current stream at its
own frame rate in the background, and later tasks (STOP, REWIND, uploads) act on it
while it plays. Replies follow the Xface byte format exactly (fae.net.xface).

Playback keeps the stream's clock: when a step takes longer than a frame period, the
next step plays the frame due by then (its held values include every frame skipped), so
a slow face plays the stream in its own duration with fewer steps rather than slower.
Every frame is still published, skipped ones with the pose of the step that covered them.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from fae.net import xface
from fae.io.frames import DenseFrame
from fae.net.connection import Connection
from fae.net.decode import FapFormatError, decode_text
from fae.net.faces import FacePool, FaceWorker, Pose
from fae.net.hub import FrameEvent, FrameHub, StreamEnd

log = logging.getLogger("fae.net")


def _log_failure(task: asyncio.Task) -> None:
    """A playback that died says so (it failed without a word)."""
    if not task.cancelled() and task.exception() is not None:
        log.error("xface playback failed", exc_info=task.exception())

STREAM = "xface"

# Tasks fae carries out; any other name (audio, scripts, KILL_APP, ...) gets ERROR 7.
HANDLED = ("UPLOAD_FAP", "LOAD_FAP", "RESUME_PLAYBACK", "STOP_PLAYBACK", "REWIND_PLAYBACK",
           "RENDER_FRAME", "ADVANCE_FRAME")


def wav_byte_count(task: xface.XfaceTask) -> int | None:
    """The audio byte count an UPLOAD_WAV task announces (its second param), or None."""
    if len(task.params) < 2:
        return None
    text = task.params[1].strip()
    return int(text) if text.isascii() and text.isdigit() and len(text) <= 12 else None


def resolve_fap_path(fap_dir: Path | None, param: str) -> Path:
    """The file a LOAD_FAP parameter names, kept inside `fap_dir`.

    Raises PermissionError when loading is disabled (no fap_dir), the path leaves
    fap_dir (absolute elsewhere, `..`, symlinks), or does not end in `.fap`;
    FileNotFoundError when there is no such file.
    """
    if fap_dir is None:
        raise PermissionError("LOAD_FAP is disabled: the server was started without --fap-dir")
    root = fap_dir.resolve()
    path = (root / param.strip()).resolve()
    if not path.is_relative_to(root):
        raise PermissionError(f"{param!r}: expected a path inside {root}")
    if path.suffix.lower() != ".fap":
        raise PermissionError(f"{param!r}: expected a .fap file")
    if not path.is_file():
        raise FileNotFoundError(f"{param!r}: no such file in {root}")
    return path


class XfaceStage:
    """State shared by all Xface clients of one server.

    faces      where the shared face comes from (taken at the first frame played)
    clients    the server's connections by client id (notifications are routed by ownerId)
    fap_dir    folder LOAD_FAP may read from, or None to refuse LOAD_FAP
    max_task   bytes per task message (an UPLOAD_FAP holds a whole file)
    max_errors error replies after which a client is closed
    """

    def __init__(self, faces: FacePool, hub: FrameHub, clients: dict[int, Connection], *,
                 fap_dir: Path | None = None, max_task: int = 8 << 20, queue_size: int = 64,
                 max_errors: int = 32) -> None:
        self.faces = faces
        self.hub = hub
        self.clients = clients
        self.fap_dir = Path(fap_dir) if fap_dir is not None else None
        self.max_task = max_task
        self.max_errors = max_errors
        self.frames: Sequence[DenseFrame] = ()
        self.fps = 25.0
        self.pos = 0
        self.last_pose: Pose | None = None
        self.last_index = 0
        self.worker: FaceWorker | None = None
        self.playback: asyncio.Task | None = None
        self.frames_applied = 0
        self.steps = 0
        self._epoch = 0  # bumped when the stream or its position changes outside playback
        self._waiting: Counter[int] = Counter()  # tasks queued or running, by client id
        self._playing_for: int | None = None  # the client whose RESUME_PLAYBACK is playing
        self._queue: asyncio.Queue = asyncio.Queue(queue_size)
        self._dispatcher: asyncio.Task | None = None

    # -- per connection ------------------------------------------------------------
    def busy_for(self, client_id: int) -> bool:
        """Whether the client waits on the stage: a task of its queued or running, or the
        playback it started still playing (its silence then is no idleness)."""
        playing = self.playback is not None and not self.playback.done()
        return self._waiting[client_id] > 0 or (playing and self._playing_for == client_id)

    async def session(self, conn: Connection, first: bytes) -> None:
        """Read tasks from one Xface client until it closes."""
        if self._dispatcher is None:
            self._dispatcher = asyncio.create_task(self._dispatch())
        splitter = xface.TaskSplitter(self.max_task)
        errors = 0
        data = first
        while data and not conn.closing:
            splitter.push(data)
            while True:
                try:
                    message = splitter.pop()
                except xface.TaskFormatError as exc:
                    log.warning("xface client %d: %s; closing", conn.client_id, exc)
                    await conn.send_and_drain(xface.error_notify_bytes())
                    return
                if message is None:
                    break
                try:
                    task = xface.parse_task(message)
                except xface.TaskFormatError as exc:
                    errors += 1
                    if await self._refuse(conn, str(exc), errors):
                        return
                    continue
                if task.name == "UPLOAD_WAV":  # audio is not played: pass over its bytes
                    count = wav_byte_count(task)
                    if count is None:
                        log.warning("xface client %d: UPLOAD_WAV: expected <param>NAME</param><param>BYTE COUNT"
                                    "</param>, got %r; closing (its audio bytes cannot be told from tasks)",
                                    conn.client_id, task.params)
                        await conn.send_and_drain(xface.error_notify_bytes())
                        return
                    splitter.skip(count)
                if task.name not in HANDLED:
                    errors += 1
                    if await self._refuse(conn, f"task {task.name!r} is not supported", errors):
                        return
                    continue
                await conn.send_and_drain(xface.notify_bytes(task.name, task.owner_id, task.task_id, xface.STATUS_QUEUED))
                self._waiting[conn.client_id] += 1
                await self._queue.put((conn.client_id, task))
            data = await conn.read()

    async def _refuse(self, conn: Connection, why: str, errors: int) -> bool:
        """Answer a task with ERROR (the client's `errors`-th); True when that is
        `max_errors` and the client is to be closed (each error costs a log line and a reply)."""
        closing = errors >= self.max_errors
        log.warning("xface client %d: %s%s", conn.client_id, why, f" (error {errors}: closing)" if closing else "")
        await conn.send_and_drain(xface.error_notify_bytes())
        return closing

    # -- the shared task queue -----------------------------------------------------
    def _route(self, task: xface.XfaceTask, status: int) -> None:
        if task.owner_id == 0:
            return
        conn = self.clients.get(task.owner_id)
        if conn is not None and conn.xface:  # a task naming a native client's id wrote into its replies
            conn.send(xface.notify_bytes(task.name, task.owner_id, task.task_id, status))

    async def _dispatch(self) -> None:
        while True:
            client_id, task = await self._queue.get()
            try:
                if task.name == "RESUME_PLAYBACK":
                    self._playing_for = client_id
                await getattr(self, "_task_" + task.name.lower())(task)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("xface task %s failed", task.name)
                self._route(task, xface.STATUS_ERROR)
            finally:
                self._waiting[client_id] -= 1
                if self._waiting[client_id] <= 0:
                    del self._waiting[client_id]

    async def _load(self, task: xface.XfaceTask, read_text) -> None:
        self._route(task, xface.STATUS_STARTED)
        if not task.params:
            log.warning("xface %s: expected one <param>", task.name)
            self._route(task, xface.STATUS_ERROR)
            return
        try:
            text, source = await asyncio.to_thread(read_text, task.params[0])
        except (OSError, UnicodeDecodeError) as exc:
            log.warning("xface %s: %s", task.name, exc)
            self._route(task, xface.STATUS_ERROR)
            return
        try:
            fps, frames = await asyncio.to_thread(decode_text, text, source)
        except FapFormatError as exc:
            log.warning("xface %s: %s", task.name, exc)
            self._route(task, xface.STATUS_ERROR)
        else:
            if not frames:  # refused as `fae play` refuses it; RESUME_PLAYBACK would find nothing
                log.warning("xface %s: %s: the stream has no frames; expected at least one", task.name, source)
                self._route(task, xface.STATUS_ERROR)
                self._route(task, xface.STATUS_FINISHED)
                return
            self.frames, self.fps, self.pos = frames, fps, 0
            self._epoch += 1
        self._route(task, xface.STATUS_FINISHED)

    async def _task_upload_fap(self, task: xface.XfaceTask) -> None:
        await self._load(task, lambda text: (text, f"UPLOAD_FAP task {task.task_id} of client {task.owner_id}"))

    async def _task_load_fap(self, task: xface.XfaceTask) -> None:
        def read(param: str) -> tuple[str, str]:
            path = resolve_fap_path(self.fap_dir, param)
            if path.stat().st_size > self.max_task:
                raise PermissionError(f"{path}: expected at most {self.max_task} bytes")
            return path.read_text(encoding="utf-8"), str(path)
        await self._load(task, read)

    async def _task_resume_playback(self, task: xface.XfaceTask) -> None:
        if not self.frames:
            log.warning("xface RESUME_PLAYBACK: no FAP stream loaded")
            self._route(task, xface.STATUS_ERROR)
            return
        self._cancel_playback()
        self.playback = asyncio.create_task(self._play(task))
        self.playback.add_done_callback(_log_failure)

    async def _task_stop_playback(self, task: xface.XfaceTask) -> None:
        self._cancel_playback()
        self.pos = 0
        self._epoch += 1
        if self.frames:
            await self._face().reset()
            await self._apply(self.frames[0])
            await self.hub.publish(StreamEnd(STREAM))
        self._route(task, xface.STATUS_FINISHED)

    async def _task_rewind_playback(self, task: xface.XfaceTask) -> None:
        self.pos = 0
        self._epoch += 1
        if self.worker is not None:
            await self.worker.reset()
        self._route(task, xface.STATUS_FINISHED)

    async def _task_render_frame(self, task: xface.XfaceTask) -> None:
        if self.last_pose is not None:
            await self.hub.publish(FrameEvent(STREAM, self.last_index, self.last_index / self.fps, self.fps,
                                              self.last_pose, self.steps))

    async def _task_advance_frame(self, task: xface.XfaceTask) -> None:
        if self.pos < len(self.frames):
            await self._apply(self.frames[self.pos])
            self.pos += 1

    # -- playback ------------------------------------------------------------------
    def _face(self) -> FaceWorker:
        if self.worker is None:
            self.worker = self.faces.take()
        return self.worker

    async def _apply(self, frame, skipped: range = range(0)) -> None:
        """One step of one frame period towards `frame`; publish it and the frames at the
        `skipped` positions before it (their held values are in `frame`'s) with the
        resulting pose."""
        frames = self.frames  # `skipped` counts this stream's frames: another may be uploaded during the step
        pose = await self._face().submit(frame, 1.0 / self.fps)
        self.steps += 1
        self.frames_applied += len(skipped) + 1
        self.last_pose, self.last_index = pose, frame.index
        for i in skipped:
            f = frames[i]
            await self.hub.publish(FrameEvent(STREAM, f.index, f.time, self.fps, pose, self.steps))
        await self.hub.publish(FrameEvent(STREAM, frame.index, frame.time, self.fps, pose, self.steps))

    async def _play(self, task: xface.XfaceTask) -> None:
        self._route(task, xface.STATUS_STARTED)
        loop = asyncio.get_running_loop()
        epoch = None
        while self.pos < len(self.frames):
            if epoch != self._epoch:  # started, rewound, or a new stream: restart the clock
                epoch, start, first, period = self._epoch, loop.time(), self.pos, 1.0 / self.fps
            due = first + int((loop.time() - start) / period)
            target = min(max(self.pos, due), len(self.frames) - 1)
            skipped = range(self.pos, target)  # the frames that fell due while the last step ran
            self.pos = target + 1
            await self._apply(self.frames[target], skipped)
            if epoch == self._epoch:
                delay = start + (self.pos - first) * period - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
        await self.hub.publish(StreamEnd(STREAM))
        self._route(task, xface.STATUS_FINISHED)

    def _cancel_playback(self) -> None:
        if self.playback is not None and not self.playback.done():
            self.playback.cancel()
        self.playback = None

    async def close(self) -> None:
        """Stop playback and the task queue; release the face."""
        self._cancel_playback()
        for t in (self._dispatcher,):
            if t is not None:
                t.cancel()
                try:
                    await t
                except (asyncio.CancelledError, Exception):
                    pass
        if self.worker is not None:
            self.worker.close()
