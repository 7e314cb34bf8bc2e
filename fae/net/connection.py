"""One client connection: its id, streams, and bounded output."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

READ_CHUNK = 65536


@dataclass
class Connection:
    """A connected client.

    client_id   counts up from 1 over the server's life, never reused (Xface ownerId)
    max_output  bytes that may wait unsent to this client; past that the client is
                treated as dead and dropped, so one that never reads cannot grow memory
    """

    client_id: int
    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    max_output: int = 1 << 20
    peer: str = field(default="")
    dropped: bool = False

    def __post_init__(self) -> None:
        if not self.peer:
            info = self.writer.get_extra_info("peername")
            self.peer = f"{info[0]}:{info[1]}" if isinstance(info, tuple) else str(info)

    @property
    def closing(self) -> bool:
        return self.dropped or self.writer.transport.is_closing()

    def send(self, data: bytes) -> bool:
        """Queue bytes without waiting; False (and the connection dropped) when it cannot."""
        if self.closing:
            return False
        if self.writer.transport.get_write_buffer_size() + len(data) > self.max_output:
            self.drop()
            return False
        self.writer.write(data)
        return True

    async def send_and_drain(self, data: bytes) -> bool:
        """Send and wait until the client has taken its share (backpressure)."""
        if not self.send(data):
            return False
        try:
            await self.writer.drain()
        except ConnectionError:
            self.dropped = True
            return False
        return True

    def drop(self) -> None:
        """Close at once, discarding unsent output."""
        self.dropped = True
        self.writer.transport.abort()
