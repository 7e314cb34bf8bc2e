"""`FapServer`: FAP streams over TCP, the native line protocol and Xface tasks on one port.

Protocol detection (docs/protocol.md): the server waits `greeting_delay` seconds for the
client's first bytes. A client that stays silent gets the Xface greeting
(`<notify name="CONNECTION_OK" .../>` and two NULs), as Xface clients wait for it. Then
the first non-blank byte decides: `<` is an Xface client, anything else a native one.

Faces: each native connection drives its own face, built by `face_factory` when its
header arrives (or ahead, `spare_faces`); the faces step on a pool of one thread per core,
each face's steps in order (fae.net.faces); all Xface clients share one face
(as in Xface). Every pose is published to subscribers (:meth:`FapServer.subscribe`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from fae.net import xface
from fae.net.connection import READ_CHUNK, Connection
from fae.net.faces import FaceFactory, FacePool
from fae.net.hub import FrameHub, Subscription
from fae.net.logbound import bound_logger
from fae.net.native import NativeSession
from fae.net.stage import XfaceStage

log = logging.getLogger("fae.net")
bound_logger()

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 50011


@dataclass(frozen=True)
class ServerLimits:
    """What one client may cost.

    greeting_delay  seconds of silence after which a client gets the Xface greeting
    max_line        bytes per native line
    max_task        bytes per Xface task (an UPLOAD_FAP carries a whole file)
    window          native frames decoded but not yet acknowledged per client before
                    reading from it pauses
    max_errors      error replies after which a connection is closed
    max_output      bytes waiting unsent to a client before it is dropped as dead
    max_clients     connections at once
    max_per_address connections at once from one IP address
    idle_timeout    seconds a client may stay silent with nothing in progress before it
                    is closed (an Xface client's playback, a native client's frames in
                    play count as in progress)
    evict_idle      when a newcomer finds no place (max_clients, or its address's
                    max_per_address), the connection idle longest is closed to make room,
                    if it has been idle at least this many seconds; otherwise the
                    newcomer is refused. So sockets that hold places and say nothing
                    cannot lock a well-behaved client out.
    """

    greeting_delay: float = 0.25
    max_line: int = 8192
    max_task: int = 8 << 20
    window: int = 1024
    max_errors: int = 32
    max_output: int = 1 << 20
    max_clients: int = 64
    max_per_address: int = 16
    idle_timeout: float = 300.0
    evict_idle: float = 1.0


class FapServer:
    """An asyncio TCP server playing FAP streams on faces.

    face_factory  builds one face (a FrameConsumer); called in a worker thread, once per
                  native stream and once for the shared Xface face
    host, port    where to listen; port 0 picks a free port (see `.port` after start)
    fap_dir       folder Xface LOAD_FAP may read .fap files from (None: LOAD_FAP refused)
    spare_faces   faces built ahead of need, so a new client's face is ready at once
                  (each costs one face's memory; 0: built when a header arrives)
    """

    def __init__(self, face_factory: FaceFactory, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *,
                 fap_dir: str | Path | None = None, limits: ServerLimits = ServerLimits(),
                 spare_faces: int = 0) -> None:
        self.face_factory = face_factory
        self.spare_faces = spare_faces
        self.faces = FacePool(face_factory, spare_faces)
        self.host = host
        self.requested_port = port
        self.limits = limits
        self.hub = FrameHub()
        self.clients: dict[int, Connection] = {}
        self.stage = XfaceStage(self.faces, self.hub, self.clients,
                                fap_dir=Path(fap_dir) if fap_dir is not None else None, max_task=limits.max_task,
                                max_errors=limits.max_errors)
        self.connections_total = 0
        self.native_frames = 0
        self.native_steps = 0
        self._next_id = 1
        self._server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task] = set()

    # -- public --------------------------------------------------------------------
    async def start(self) -> None:
        """Bind and start accepting."""
        self._server = await asyncio.start_server(self._on_connect, self.host, self.requested_port)
        self._port = self._server.sockets[0].getsockname()[1]

    @property
    def port(self) -> int:
        """The port actually bound (after start)."""
        if self._server is None:
            raise RuntimeError("FapServer.port: the server is not started")
        return self._port

    def subscribe(self, maxsize: int = 8, lossless: bool = False) -> Subscription:
        """Receive every FrameEvent/StreamEnd the server produces (see fae.net.hub)."""
        return self.hub.subscribe(maxsize=maxsize, lossless=lossless)

    def stats(self) -> dict[str, int]:
        """Totals so far: connections, frames acknowledged and simulation steps taken.

        connections      clients accepted
        native_frames    native frames acknowledged (streams that have ended)
        native_steps     face steps those frames took (fewer when faces fell behind)
        xface_frames     frames played by Xface playback / ADVANCE_FRAME
        xface_steps      face steps those took
        """
        return {"connections": self.connections_total, "native_frames": self.native_frames,
                "native_steps": self.native_steps, "xface_frames": self.stage.frames_applied,
                "xface_steps": self.stage.steps}

    async def serve_until(self, stop: asyncio.Event) -> None:
        """Serve until `stop` is set, then close gracefully."""
        if self._server is None:
            await self.start()
        try:
            await stop.wait()
        finally:
            await self.close()

    async def close(self) -> None:
        """Stop accepting, close every connection, stop playback, end subscriptions."""
        if self._server is not None:
            self._server.close()
        for task in list(self._handlers):
            task.cancel()
        if self._handlers:
            await asyncio.gather(*self._handlers, return_exceptions=True)
        await self.stage.close()
        self.faces.close()
        await self.hub.close()
        if self._server is not None:
            await self._server.wait_closed()

    # -- connections ---------------------------------------------------------------
    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        self._handlers.add(task)
        client_id = self._next_id
        self._next_id += 1
        self.connections_total += 1
        conn = Connection(client_id, reader, writer, max_output=self.limits.max_output,
                          idle_timeout=self.limits.idle_timeout)
        try:
            if not self._make_room(conn):
                return
            self.clients[client_id] = conn
            first = await self._first_bytes(conn)
            if not first:
                return
            if first.lstrip()[:1] == b"<":
                conn.xface = True
                conn.busy = lambda: self.stage.busy_for(client_id)
                await self.stage.session(conn, first)
            else:
                conn.xface = False
                session = NativeSession(conn, self.faces, self.hub, window=self.limits.window,
                                        max_line=self.limits.max_line, max_errors=self.limits.max_errors)
                conn.busy = lambda: session.unacknowledged > 0
                try:
                    await session.run(first)
                finally:
                    self.native_frames += session.frames_done
                    self.native_steps += session.steps
        except (ConnectionError, asyncio.CancelledError):
            pass
        except Exception:
            log.exception("client %d (%s): unexpected failure", client_id, conn.peer)
        finally:
            self.clients.pop(client_id, None)
            self._handlers.discard(task)
            writer.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.wait_closed(), 1.0)

    def _make_room(self, conn: Connection) -> bool:
        """Whether `conn` may stay: there is a place for it, or one was made by closing the
        connection idle longest (of its own address when that address is at its cap)."""
        limits = self.limits
        same = [c for c in self.clients.values() if c.address == conn.address]
        if len(same) >= limits.max_per_address:
            candidates, why = same, f"{len(same)} connections from {conn.address}"
        elif len(self.clients) >= limits.max_clients:
            candidates, why = list(self.clients.values()), f"{len(self.clients)} clients connected"
        else:
            return True
        idlest = max(candidates, key=lambda c: c.idle_seconds)
        idle = idlest.idle_seconds
        if idle < limits.evict_idle:
            log.warning("client %d (%s): refused, %s and none idle", conn.client_id, conn.peer, why)
            return False
        log.warning("client %d (%s): %s; closing client %d (%s), idle for %.1f s, to make room",
                    conn.client_id, conn.peer, why, idlest.client_id, idlest.peer, idle)
        self.clients.pop(idlest.client_id, None)
        idlest.drop()
        return True

    async def _first_bytes(self, conn: Connection) -> bytes:
        """Bytes up to and including the first non-blank one (b"" if the client left or
        stayed silent for the idle timeout after its greeting)."""
        greeted = False
        data = b""
        while not data.strip():
            if len(data) > self.limits.max_line:
                return b""
            try:
                chunk = await asyncio.wait_for(conn.reader.read(READ_CHUNK), self.limits.greeting_delay)
            except asyncio.TimeoutError:
                greeted = conn.xface = True  # silent: an Xface client waits for its greeting
                conn.send(xface.notify_bytes("CONNECTION_OK", conn.client_id, 0, xface.STATUS_UNKNOWN))
                break
            if not chunk:
                return b""
            conn.last_active = time.monotonic()
            data += chunk
        while not data.strip():  # greeted: an Xface client may now take its time
            if len(data) > self.limits.max_line:
                return b""
            chunk = await conn.read()
            if not chunk:
                return b""
            data += chunk
        if data.lstrip()[:1] == b"<" and not greeted:
            conn.send(xface.notify_bytes("CONNECTION_OK", conn.client_id, 0, xface.STATUS_UNKNOWN))
        return data
