"""One client connection: its id, reads with an idle timeout, and bounded output."""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field
from typing import Callable

READ_CHUNK = 65536
# seconds a reply may wait on a client's full socket (the client taking too little of what it
# was sent) before the client is closed: one that sent frames and never read was waited on
# for ever, counted busy, and 16 of them locked every other client of their address out
STALLED_SECONDS = 60.0

log = logging.getLogger("fae.net")


@dataclass
class Connection:
    """A connected client.

    client_id     counts up from 1 over the server's life, never reused (Xface ownerId)
    max_output    bytes that may wait unsent to this client; past that the client is
                  treated as dead and dropped, so one that never reads cannot grow memory
    idle_timeout  seconds a read may wait for the client's next bytes while the client
                  has nothing in progress on the server (None: no limit); then the
                  connection is closed, so silent sockets cannot hold places for ever
    busy          tells whether the client is waiting on the server (frames being played,
                  a playback it started); a busy client is never timed out
    last_active   time.monotonic() of the client's latest bytes (or of its connection)
    xface         the client may speak Xface's tasks (greeted after its silence, or its first
                  byte was `<`): only such a client takes Xface notifications routed by
                  ownerId (a native client's replies were written into by another's task)
    """

    client_id: int
    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    max_output: int = 1 << 20
    idle_timeout: float | None = None
    peer: str = field(default="")
    dropped: bool = False
    busy: Callable[[], bool] = field(default=lambda: False)
    last_active: float = field(default_factory=time.monotonic)
    xface: bool = False

    def __post_init__(self) -> None:
        info = self.writer.get_extra_info("peername")
        self.address = info[0] if isinstance(info, tuple) else str(info)
        if not self.peer:
            self.peer = f"{info[0]}:{info[1]}" if isinstance(info, tuple) else str(info)

    @property
    def closing(self) -> bool:
        return self.dropped or self.writer.transport.is_closing()

    @property
    def idle_seconds(self) -> float:
        """Seconds since the client last sent anything (0 while it is busy)."""
        return 0.0 if self.busy() else time.monotonic() - self.last_active

    async def read(self, timeout: float | None = None) -> bytes:
        """The client's next bytes; b"" when it has closed, or has been idle for
        `timeout` (default: idle_timeout) seconds with nothing in progress."""
        limit = self.idle_timeout if timeout is None else timeout
        while True:
            try:
                data = await asyncio.wait_for(self.reader.read(READ_CHUNK), limit)
            except asyncio.TimeoutError:
                if self.busy():
                    continue
                log.warning("client %d (%s): idle for %g s; closing", self.client_id, self.peer, limit)
                return b""
            self.last_active = time.monotonic()
            return data

    def send(self, data: bytes) -> bool:
        """Queue bytes without waiting; False (and the connection dropped) when it cannot."""
        if self.closing:
            return False
        if self.writer.transport.get_write_buffer_size() + len(data) > self.max_output:
            self.drop()
            return False
        self.writer.write(data)
        return True

    async def send_and_drain(self, data: bytes, stalled: float | None = None) -> bool:
        """Send and wait until the client has taken its share (backpressure); a client whose
        socket stays too full to take this reply for `stalled` seconds (default
        STALLED_SECONDS) is closed (False)."""
        if not self.send(data):
            return False
        stalled = STALLED_SECONDS if stalled is None else stalled
        try:
            await asyncio.wait_for(self.writer.drain(), stalled)
        except asyncio.TimeoutError:
            log.warning("client %d (%s): its replies have waited %g s on a full socket; closing", self.client_id,
                        self.peer, stalled)
            self.drop()
            return False
        except ConnectionError:
            self.dropped = True
            return False
        return True

    def drop(self) -> None:
        """Close at once, discarding unsent output."""
        self.dropped = True
        self.writer.transport.abort()
