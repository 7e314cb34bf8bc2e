"""The native protocol: a .fap stream sent line by line, each frame acknowledged.

The client sends exactly the .fap file format (header line, then mask/values line
pairs). The server answers, in the order of the lines:

    ok header <fps>          the header was read and the face is ready
    ok <frame number>        that frame's pose is computed (and published)
    error <line>: <what was expected>

A frame's ack is written once its pose exists, so the time from sending a values line to
reading its `ok` is the frame's latency. At most `window` frames are in flight per client;
beyond that the server stops reading from that client (TCP backpressure), and it stops
computing for a client that does not read its acks, so memory per client stays bounded.
"""

from __future__ import annotations

import asyncio
import logging

from fae.net.connection import READ_CHUNK, Connection
from fae.net.decode import FapFormatError, HeaderRead, StreamDecoder
from fae.net.faces import FaceFactory, FaceWorker
from fae.net.hub import FrameEvent, FrameHub, StreamEnd
from fae.net.lines import LineSplitter

log = logging.getLogger("fae.net")

_END = object()


class NativeSession:
    """Serve one native client until it closes, errs too often, or the server stops.

    window      frames in flight (read but not yet acknowledged) per client
    max_line    bytes per line
    max_errors  error replies after which the server says so and closes
    """

    def __init__(self, conn: Connection, face_factory: FaceFactory, hub: FrameHub, *,
                 window: int = 32, max_line: int = 8192, max_errors: int = 32) -> None:
        self.conn = conn
        self.stream = f"native-{conn.client_id}"
        self.face_factory = face_factory
        self.hub = hub
        self.window = window
        self.max_errors = max_errors
        self.splitter = LineSplitter(max_line)
        self.decoder = StreamDecoder(source_name=f"{conn.peer} ({self.stream})")
        self.worker: FaceWorker | None = None
        self.frames_done = 0
        self.errors = 0
        self._stop_reading = False

    async def run(self, first: bytes) -> None:
        """Serve the client; `first` holds the bytes already read from it."""
        acks: asyncio.Queue = asyncio.Queue(self.window)
        ack_task = asyncio.create_task(self._ack_loop(acks))
        try:
            data = first
            while data and not self._stop_reading:
                for line in self.splitter.feed(data):
                    item = self._handle_line(line)
                    if item is not None:
                        await acks.put(item)
                    if self._stop_reading:
                        break
                if self._stop_reading or self.conn.closing:
                    break
                data = await self.conn.reader.read(READ_CHUNK)
            if not data and not self._stop_reading and (self.splitter.pending or self.decoder.in_frame):
                number = self.splitter.line_count + 1
                await acks.put(("error", number, "stream ended inside a frame; expected the rest of the frame"))
            await acks.put(_END)
            await ack_task
        finally:
            if not ack_task.done():
                ack_task.cancel()
            if self.worker is not None:
                self.worker.close()
                await self.hub.publish(StreamEnd(self.stream))

    def _error(self, number: int, message: str) -> tuple:
        self.errors += 1
        if self.errors >= self.max_errors:
            self._stop_reading = True
            message += f" (error {self.errors}: closing)"
        return ("error", number, message)

    def _handle_line(self, line) -> tuple | None:
        if line.text is None:
            self.decoder.skip_line(line.number)
            return self._error(line.number, line.problem)
        try:
            out = self.decoder.feed(line.text, line.number)
        except FapFormatError as exc:
            shown = exc.token if exc.token is None or len(exc.token) <= 40 else exc.token[:37] + "..."
            what = f"expected {exc.expected}" if shown is None else f"token {shown!r}: expected {exc.expected}"
            return self._error(exc.line or line.number, what)
        if out is None:
            return None
        if isinstance(out, HeaderRead):
            self.worker = FaceWorker(self.face_factory, name=f"fae-{self.stream}")
            return ("header", line.number, out.fps, self.worker)
        return ("frame", line.number, out, self.worker.submit(out.dense, out.dt))

    async def _ack_loop(self, acks: asyncio.Queue) -> None:
        conn = self.conn
        while (item := await acks.get()) is not _END:
            kind, number = item[0], item[1]
            if conn.closing:
                continue  # keep taking items so the reader never waits on a dead client
            if kind == "header":
                try:
                    await item[3].ready()
                    reply = f"ok header {item[2]:g}\n"
                except Exception as exc:  # the face could not be built: say so and close
                    log.exception("%s: building the face failed", self.stream)
                    reply = f"error {number}: the server could not build a face ({type(exc).__name__}: {exc})\n"
                    self._stop_reading = True
            elif kind == "frame":
                frame, future = item[2], item[3]
                try:
                    pose = await future
                except Exception as exc:
                    log.exception("%s: step failed at line %d", self.stream, number)
                    reply = f"error {number}: the face could not play frame {frame.number} ({type(exc).__name__}: {exc})\n"
                    self._stop_reading = True
                else:
                    self.frames_done += 1
                    await self.hub.publish(FrameEvent(self.stream, frame.number, frame.dense.time, self.decoder.fps, pose))
                    reply = f"ok {frame.number}\n"
            else:
                reply = f"error {number}: {item[2]}\n"
            await conn.send_and_drain(reply.encode("utf-8"))
