"""The native protocol: a .fap stream sent line by line, each frame acknowledged.

The client sends exactly the .fap file format (header line, then mask/values line
pairs). The server answers:

    ok header <fps>            the header was read and the face is ready
    error <line>: <what>       line <line> was rejected (sent as soon as the line is read)
    ok <frame number> <step>   positions that include this frame are ready (and published);
                               <step> counts the face's simulation steps (1, 2, ...)
    done <frames> frames <steps> steps <errors> errors
                               after the client half-closed and everything was answered

Every line is decoded and validated as soon as it arrives. The face simulates at its own
pace: while it computes one step, the frames that arrive are held, and its next step
uses the latest held values (FAP semantics: unsent values hold) for all of them at once,
with the latest frame's own dt. So a client sending faster than the face can simulate
gets every frame acknowledged (several frames share a step number) with a latency of at
most about two steps, instead of a queue that grows without end. See docs/protocol.md.

At most `window` frames are decoded but not yet acknowledged per client; beyond that the
server stops reading from that client (TCP backpressure), and a client that does not read
its replies stops its own session only, so memory per client stays bounded.
"""

from __future__ import annotations

import asyncio
import logging

from fae.net.connection import Connection
from fae.net.decode import FapFormatError, HeaderRead, StreamDecoder, StreamFrame
from fae.net.faces import FacePool, FaceWorker
from fae.net.hub import FrameEvent, FrameHub, StreamEnd
from fae.net.lines import LineSplitter

log = logging.getLogger("fae.net")

YIELD_LINES = 32  # lines decoded between chances for other tasks to run (~ a few ms)


class NativeSession:
    """Serve one native client until it closes, errs too often, or the server stops.

    faces       where the client's face comes from (taken when its header arrives)

    window      frames decoded but not yet acknowledged per client before reading pauses
    max_line    bytes per line
    max_errors  error replies after which the server says so and closes

    After `run`: frames_done (frames acknowledged), steps (simulation steps they took),
    errors (error replies).
    """

    def __init__(self, conn: Connection, faces: FacePool, hub: FrameHub, *,
                 window: int = 1024, max_line: int = 8192, max_errors: int = 32) -> None:
        if window < 1:
            raise ValueError(f"window: expected >= 1 frame, got {window}")
        self.conn = conn
        self.stream = f"native-{conn.client_id}"
        self.faces = faces
        self.hub = hub
        self.window = window
        self.max_errors = max_errors
        self.splitter = LineSplitter(max_line)
        self.decoder = StreamDecoder(source_name=f"{conn.peer} ({self.stream})")
        self.worker: FaceWorker | None = None
        self.frames_done = 0
        self.steps = 0
        self.errors = 0
        self._pending: list[tuple[int, StreamFrame]] = []  # (values line number, frame)
        self._in_step = 0
        self._wake = asyncio.Event()   # frames arrived, or the stream ended
        self._room = asyncio.Event()   # frames were acknowledged
        self._ended = False
        self._stop_reading = False
        self._stepper: asyncio.Task | None = None

    @property
    def unacknowledged(self) -> int:
        """Frames decoded but not yet acknowledged."""
        return len(self._pending) + self._in_step

    async def run(self, first: bytes) -> None:
        """Serve the client; `first` holds the bytes already read from it."""
        try:
            data = first
            while data and not self._stop_reading:
                for line in self.splitter.feed(data):
                    await self._handle_line(line)
                    if self._stop_reading:
                        break
                    if line.number % YIELD_LINES == 0:
                        # Decoding a full read takes tens of ms and a read of buffered bytes
                        # does not yield: let the face's finished step and other clients in.
                        await asyncio.sleep(0)
                if self._stop_reading or self.conn.closing:
                    break
                while self.unacknowledged >= self.window and not self._stopped():
                    self._room.clear()
                    await self._room.wait()
                data = await self.conn.read()
            clean_end = not data and not self._stop_reading and not self.conn.closing
            if clean_end and (self.splitter.pending or self.decoder.in_frame):
                await self._error(self.splitter.line_count + 1,
                                  "stream ended inside a frame; expected the rest of the frame")
            await self._finish_steps()
            if clean_end:  # also after no header, or a bad one: every half-close is answered
                await self._reply(f"done {self.frames_done} frames {self.steps} steps {self.errors} errors\n")
        finally:
            if self._stepper is not None and not self._stepper.done():
                self._stepper.cancel()
            if self.worker is not None:
                self.worker.close()
                await self.hub.publish(StreamEnd(self.stream))

    def _stopped(self) -> bool:
        return self._stop_reading or self.conn.closing or (self._stepper is not None and self._stepper.done())

    async def _reply(self, text: str) -> None:
        await self.conn.send_and_drain(text.encode("utf-8"))

    async def _error(self, number: int, message: str) -> None:
        self.errors += 1
        if self.errors >= self.max_errors:
            self._stop_reading = True
            message += f" (error {self.errors}: closing)"
        await self._reply(f"error {number}: {message}\n")

    async def _handle_line(self, line) -> None:
        if line.text is None:
            self.decoder.skip_line(line.number)
            await self._error(line.number, line.problem)
            return
        try:
            out = self.decoder.feed(line.text, line.number)
        except FapFormatError as exc:
            shown = exc.token if exc.token is None or len(exc.token) <= 40 else exc.token[:37] + "..."
            what = f"expected {exc.expected}" if shown is None else f"token {shown!r}: expected {exc.expected}"
            await self._error(exc.line or line.number, what)
            return
        if out is None:
            return
        if isinstance(out, HeaderRead):
            await self._start_face(line.number, out.fps)
            return
        self._pending.append((line.number, out))
        self._wake.set()

    async def _start_face(self, number: int, fps: float) -> None:
        """Build the face (reading waits for it: nothing can be played before) and say so."""
        self.worker = self.faces.take()
        try:
            await self.worker.ready()
        except Exception as exc:
            log.exception("%s: building the face failed", self.stream)
            self._stop_reading = True
            await self._reply(f"error {number}: the server could not build a face ({type(exc).__name__}: {exc})\n")
            return
        self._stepper = asyncio.create_task(self._step_loop())
        await self._reply(f"ok header {fps:g}\n")

    async def _finish_steps(self) -> None:
        """Let the face answer every frame read so far (none if the client is gone)."""
        self._ended = True
        self._wake.set()
        if self._stepper is not None:
            if self.conn.closing:
                self._stepper.cancel()
            try:
                await self._stepper
            except asyncio.CancelledError:
                if not self.conn.closing:
                    raise

    async def _step_loop(self) -> None:
        """Step the face once per batch of frames that arrived during its previous step."""
        conn = self.conn
        while True:
            if not self._pending:
                if self._ended:
                    return
                self._wake.clear()
                await self._wake.wait()
                continue
            batch, self._pending = self._pending, []
            self._in_step = len(batch)
            number, latest = batch[-1]
            try:
                pose = await self.worker.submit(latest.dense, latest.dt)
            except Exception as exc:
                log.exception("%s: step failed at frame %d", self.stream, latest.number)
                self._stop_reading = True
                self._room.set()
                await self._reply(f"error {number}: the face could not play frame {latest.number} "
                                  f"({type(exc).__name__}: {exc}); closing\n")
                return
            self.steps += 1
            fps = self.decoder.fps
            for _, frame in batch:
                await self.hub.publish(FrameEvent(self.stream, frame.number, frame.dense.time, fps, pose, self.steps))
            self._in_step = 0
            self.frames_done += len(batch)
            self._room.set()
            if conn.closing:
                return
            await self._reply("".join(f"ok {frame.number} {self.steps}\n" for _, frame in batch))
