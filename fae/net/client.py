"""A native-protocol client: stream a .fap text frame by frame, time every acknowledgement."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

import numpy as np

from fae.net.connection import READ_CHUNK

MIN_REPLY_FPS, MAX_REPLY_FPS = 1e-3, 1e4  # frames/s a server's header reply may name (the reader's range)
CLOSE_SECONDS = 1.0  # the longest a finished connection is waited on to close
UNKNOWN_KEPT = 3  # reply lines outside the protocol kept for the report


@dataclass
class SendReport:
    """What the server said about one streamed file.

    frames_sent   frames (mask/values pairs) sent
    frames_ok     frames acknowledged with `ok`
    steps         face simulation steps those frames took (the server's count; fewer than
                  frames_ok when the face fell behind and held frames were coalesced)
    errors        the server's `error ...` lines, in order
    latencies     (frames_ok,) float64 seconds from sending a frame's values line to
                  reading its `ok`
    frame_steps   (frames_ok,) int64 the step number each `ok` named, in reply order
    started       time.perf_counter() when the first frame was sent
    elapsed       seconds from the first frame sent to the last reply read
    fps           the stream's frame rate from the server's header reply (0 if none)
    done          whether the server's closing `done ...` line came (it follows the last
                  reply to a stream sent whole)
    unknown       reply lines that are none of the protocol's (not a fae server), the first
                  few
    header_wait   seconds the header's reply was waited for in vain (0: it came, or the
                  connection closed first)
    """

    frames_sent: int = 0
    frames_ok: int = 0
    steps: int = 0
    errors: list[str] = field(default_factory=list)
    latencies: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frame_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    started: float = 0.0
    elapsed: float = 0.0
    fps: float = 0.0
    header_ok: bool = False
    done: bool = False
    unknown: list[str] = field(default_factory=list)
    header_wait: float = 0.0

    @property
    def frames_per_second(self) -> float:
        return self.frames_ok / self.elapsed if self.elapsed > 0 else 0.0

    def latency_ms(self, q: float) -> float:
        """The q-th percentile (0..100) of the latencies, milliseconds (nan if none)."""
        return float(np.percentile(self.latencies, q) * 1e3) if self.latencies.size else float("nan")

    @property
    def complete(self) -> bool:
        """Every frame acknowledged, no error."""
        return self.header_ok and not self.errors and self.frames_ok == self.frames_sent

    def problem(self) -> str | None:
        """Why these replies are not a fae server's answer to the whole stream, or None:
        a summary of such replies ("0/0 frames ok", "100/48 frames ok") says nothing."""
        seen = f" (it sent {ascii(self.unknown[0])[:70]})" if self.unknown else ""
        if self.errors:
            return None  # the server's own words say what went wrong
        if not self.header_ok:
            waited = f" for {self.header_wait:g} s" if self.header_wait else ""
            return f"no reply to the stream's header{waited}: not a fae server, or it closed the connection{seen}"
        if self.frames_ok > self.frames_sent:
            return f"{self.frames_ok} frames acknowledged of {self.frames_sent} sent: not a fae server{seen}"
        if not self.done:
            return (f"the connection closed after {self.frames_ok} of {self.frames_sent} frames were "
                    f"acknowledged, without the server's closing `done` line{seen}")
        if self.frames_ok < self.frames_sent:
            return (f"the server said `done` after acknowledging {self.frames_ok} of {self.frames_sent} frames, "
                    f"with no error{seen}")
        return None

    def summary(self) -> str:
        return (f"{self.frames_ok}/{self.frames_sent} frames ok in {self.steps} face steps, "
                f"{len(self.errors)} errors, {self.frames_per_second:.0f} frames/s, latency p50 {self.latency_ms(50):.2f} ms, "
                f"p99 {self.latency_ms(99):.2f} ms")


def split_fap_text(text: str) -> tuple[str, list[tuple[str, str]]]:
    """(header line, [(mask line, values line), ...]) of a .fap text.

    Blank and `#` comment lines are left out; no other check is made (the server judges
    the content), except that lines must pair up.
    """
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ValueError("expected a .fap text with a header line, got no lines")
    body = lines[1:]
    if len(body) % 2:
        raise ValueError(f"expected mask/values line pairs after the header, got {len(body)} lines")
    return lines[0], list(zip(body[0::2], body[1::2]))


async def send_fap(text: str, host: str = "127.0.0.1", port: int = 50011, *, rate: str = "max",
                   timeout: float = 30.0) -> SendReport:
    """Stream `text` to a fae server and collect its replies.

    rate     "max": send as fast as the server takes them (TCP backpressure);
             "realtime": frame k is sent k / fps seconds after the first
    timeout  seconds to wait for any one reply before giving up
    """
    if rate not in ("max", "realtime"):
        raise ValueError(f"rate: expected 'max' or 'realtime', got {rate!r}")
    header, frames = split_fap_text(text)
    reader, writer = await asyncio.open_connection(host, port)
    report = SendReport()
    sent_at: dict[str, list[float]] = {}
    latencies: list[float] = []
    frame_steps: list[int] = []
    header_seen = asyncio.Event()
    start = [0.0]

    async def receive() -> None:
        buf = b""
        while True:  # until the server closes, after answering everything sent
            try:
                chunk = await asyncio.wait_for(reader.read(READ_CHUNK), timeout)
            except asyncio.TimeoutError:
                raise asyncio.TimeoutError(f"no reply for {timeout:g} s") from None
            if not chunk:
                break
            buf += chunk
            if buf.startswith(b"<notify"):  # the Xface greeting, sent to silent clients
                end = buf.find(b"\0\0")
                if end < 0:
                    continue
                buf = buf[end + 2:]
            *lines, buf = buf.split(b"\n")
            now = time.perf_counter()
            for raw in lines:
                line = raw.decode("utf-8", "replace").strip()
                if line.startswith("ok header"):
                    report.header_ok = True
                    parts = line.split()
                    try:
                        report.fps = float(parts[2]) if len(parts) > 2 else 0.0
                    except ValueError:  # not a rate: paced at 25 frames/s like a missing one
                        report.fps = 0.0
                    header_seen.set()
                elif line.startswith("ok "):
                    parts = line.split()
                    times = sent_at.get(parts[1])
                    if times:
                        latencies.append(now - times.pop(0))
                    report.frames_ok += 1
                    if len(parts) > 2 and parts[2].isdigit():
                        frame_steps.append(int(parts[2]))
                        report.steps = max(report.steps, frame_steps[-1])
                elif line.startswith("error"):
                    report.errors.append(line)
                    header_seen.set()
                    if "closing" in line:
                        return
                elif line.startswith("done "):
                    report.done = True
                elif line and len(report.unknown) < UNKNOWN_KEPT:
                    report.unknown.append(line)
            report.elapsed = now - start[0]

    high_water = writer.transport.get_write_buffer_limits()[1]

    async def sent() -> None:  # a server that stops reading is given `timeout` seconds, as one that stops answering
        if writer.transport.get_write_buffer_size() <= high_water:
            await writer.drain()  # returns at once: nothing to wait for
            return
        try:
            await asyncio.wait_for(writer.drain(), timeout)
        except asyncio.TimeoutError:
            raise asyncio.TimeoutError(f"the server took nothing for {timeout:g} s") from None

    receiver = asyncio.create_task(receive())
    finished = False
    try:
        writer.write(header.encode("utf-8") + b"\n")
        await sent()
        header_wait = asyncio.create_task(header_seen.wait())
        await asyncio.wait([receiver, header_wait], timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
        header_wait.cancel()
        if not header_seen.is_set():
            if receiver.done() and receiver.exception() is not None:
                raise receiver.exception()  # the connection's own failure (reset, ...) says most
            # no answer a fae server gives (report.problem says what came instead); the
            # frames are not sent, the finally below lets go of the connection
            report.header_wait = 0.0 if receiver.done() else timeout
            return report
        # the server's rate paces "realtime"; one beyond any stream's (a reply of 1e-300) is not taken
        fps = report.fps if MIN_REPLY_FPS <= report.fps <= MAX_REPLY_FPS else 25.0
        start[0] = report.started = time.perf_counter()
        try:
            for k, (mask, values) in enumerate(frames):
                if receiver.done():
                    break
                if rate == "realtime":
                    delay = start[0] + k / fps - time.perf_counter()
                    if delay > 0:
                        await asyncio.sleep(delay)
                number = values.split(maxsplit=1)[0] if values.split() else ""
                sent_at.setdefault(number, []).append(time.perf_counter())
                writer.write(f"{mask}\n{values}\n".encode("utf-8"))
                report.frames_sent += 1
                await sent()
            if writer.can_write_eof():
                writer.write_eof()
        except OSError:  # a server that closed on our errors: its own words say why (not "not connected")
            if not (receiver.done() or report.errors):
                raise
        # each reply within `timeout` (the receiver's own wait); the tail as a whole may take
        # longer (a timeout on it cut a server still answering, or hung as it raced the last read)
        await receiver
        finished = True
    finally:
        if not receiver.done():
            receiver.cancel()
        if not finished:  # what is still unsent is dropped: a close would wait for it (for ever)
            writer.transport.abort()
        writer.close()
        try:
            await asyncio.wait_for(writer.wait_closed(), CLOSE_SECONDS)
        except (ConnectionError, asyncio.TimeoutError):
            pass
    report.latencies = np.asarray(latencies, dtype=np.float64)
    report.frame_steps = np.asarray(frame_steps, dtype=np.int64)
    return report
