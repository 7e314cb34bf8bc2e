"""A live view of the faces stepping in `fae serve`, in the browser.

    LiveView(model, subscribe, host="127.0.0.1", port=8080, three_dir=None)
    await view.start(); view.url; await view.close()

One asyncio server (the `websockets` library) answers plain HTTP and WebSockets on one
port: GET / is the page (fae/net/view_page/index.html), /three/... the three.js files
from npm (`three_dir`: its package folder, see find_three), and /ws the WebSocket.

On /ws a page first gets the head as one JSON text message:

    {"type": "head", "skin": {"positions": [x, y, z, ...] metres, "faces": [i, j, k, ...],
     "color": [r, g, b, a]}, "parts": [{"name", "bone", "positions", "faces", "color"}]}

A head with a skin texture also sends "uv" [u, v, ...], "texture" (a data: URL of the PNG)
and "seam" [i, ...]: the skin's positions then end with copies of the vertices whose
triangles cross the texture's seam (fae.mesh.wrapped_seam), and a page sets each copy from
vertex seam[k] of every frame. With the colours fae draws the skin in, it also sends
"colors" [r, g, b, ...]: the texture's factors (1 on the skin, darker inside the mouth).

then one binary message per frame it is shown: a little-endian uint32 n, n bytes of JSON
{"stream", "index", "time", "fps", "step", "bones": {bone: 16 floats, column-major}},
zero padding to a multiple of 4, then the skin's positions as float32 (V x 3, metres,
face frame). A page answers each frame with the text "ack" once it has shown it, and is
sent a frame only while fewer than IN_FLIGHT of its frames are unanswered. Each page has its
own lossy subscription to the server's frames (fae.net.hub): a slow page skips frames (it is
sent the latest, not a backlog: without the answers, a page drawing 10 frames a second of a
25 fps stream fell 4 s behind), never slows a stream; a page that closes or breaks leaves
the streams and the other pages as they were. A client whose unread replies pile up past
MAX_PAGE_BUFFER (a ping flood: 35 MB/s) is cut off.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import mimetypes
import os
import struct
from http import HTTPStatus
from pathlib import Path

import numpy as np

from fae.net.hub import FrameEvent, StreamEnd

log = logging.getLogger("fae.net")  # the server's logger: its records are bounded (fae.net.logbound)
IN_FLIGHT = 2  # frames a page may hold unanswered
# ended streams' last poses a page may be owed: past these the oldest are dropped, their ends
# kept (a page that never read kept every ended stream's last pose: 370 MB -> 1.4 GB over
# 3,000 streams); and ends (a stream's name each), past which the oldest are dropped
MAX_OWED_END_FRAMES = 16
MAX_OWED_ENDS = 100_000
MAX_PAGE_BUFFER = 16 * 2**20  # bytes of replies a page leaves unread before it is cut off
CLOSE_SECONDS = 1.0  # the longest a closing page is waited for
PAGE_DIR = Path(__file__).resolve().parent / "view_page"
THREE_FILES = ("build", "examples/jsm")  # the only folders of the three package served
HIDDEN_PARTS = ("cranium", "mandible")  # always under the skin: not sent


def find_three() -> Path | None:
    """The three.js npm package folder: $FAE_THREE_DIR, else node_modules/three beside the
    project's tools (where `make install` puts it) or in the working directory."""
    candidates = []
    if os.environ.get("FAE_THREE_DIR"):
        candidates.append(Path(os.environ["FAE_THREE_DIR"]))
    root = Path(__file__).resolve().parents[2]
    candidates += [root / "tools" / "node_modules" / "three", Path.cwd() / "node_modules" / "three"]
    for c in candidates:
        if (c / "build" / "three.module.js").is_file():
            return c
    return None


def head_message(model, skin_colors=None) -> str:
    """The JSON text message describing the head (see the module docstring). skin_colors
    (V, 3) linear RGB as fae draws the skin (fae.render.renderer.skin_colors): on a textured
    head they become the texture's factors ("colors": 1 on the skin, darker in the mouth)."""
    def rounded(a):
        return np.round(np.asarray(a, dtype=np.float64), 6).ravel().tolist()

    skin = {"positions": rounded(model.skin_vertices), "faces": np.asarray(model.skin_faces).ravel().tolist(),
            "color": np.asarray(model.skin_color, dtype=float).ravel()[:4].tolist()
            if model.skin_color is not None and np.size(model.skin_color) >= 3 else [0.85, 0.65, 0.55, 1.0]}
    if getattr(model, "skin_texture", None) is not None:
        import base64

        from fae.io.facemodel_gltf import png_bytes, texture_factors
        from fae.mesh import wrapped_seam

        faces, seam, uv = wrapped_seam(model.skin_faces, model.skin_uv)
        V = np.asarray(model.skin_vertices, dtype=np.float64)
        skin.update({"positions": rounded(np.concatenate([V, V[seam]])), "faces": faces.ravel().tolist(),
                     "uv": np.round(uv.astype(np.float64), 5).ravel().tolist(), "seam": seam.tolist(),
                     "texture": "data:image/png;base64," + base64.b64encode(png_bytes(model.skin_texture)).decode(),
                     "color": [1.0, 1.0, 1.0, 1.0]})
        if skin_colors is not None:
            factors = texture_factors(skin_colors, model.skin_color)
            skin["colors"] = np.round(np.concatenate([factors, factors[seam]]), 3).ravel().tolist()
    parts = []
    for name, part in model.parts.items():
        if name in HIDDEN_PARTS:
            continue
        entry = {"name": name, "bone": part.bone, "positions": rounded(part.vertices),
                 "faces": np.asarray(part.faces).ravel().tolist(),
                 "color": np.asarray(part.color, dtype=float).ravel()[:4].tolist()}
        if part.vertex_colors is not None:
            entry["colors"] = np.round(np.asarray(part.vertex_colors, dtype=float)[:, :3], 3).ravel().tolist()
        parts.append(entry)
    return json.dumps({"type": "head", "skin": skin, "parts": parts}, separators=(",", ":"))


def frame_message(event: FrameEvent) -> bytes:
    """The binary message of one frame (see the module docstring)."""
    bones = {name: np.asarray(T, dtype=np.float64).T.ravel().round(7).tolist()
             for name, T in (event.pose.bone_transforms or {}).items()}
    meta = json.dumps({"stream": event.stream, "index": int(event.index), "time": float(event.time),
                       "fps": float(event.fps), "step": int(event.step), "bones": bones},
                      separators=(",", ":")).encode()
    meta += b" " * (-(4 + len(meta)) % 4)
    return struct.pack("<I", len(meta)) + meta + np.asarray(event.pose.skin_vertices, dtype="<f4").tobytes()


class LiveView:
    """The page and its WebSocket for the server's frames (see the module docstring).

    subscribe: a callable returning a new lossy subscription (FapServer.subscribe);
    three_dir: the three.js package folder (find_three() when None)."""

    def __init__(self, model, subscribe, host: str = "127.0.0.1", port: int = 8080, three_dir: Path | None = None,
                 skin_colors=None):
        self.model = model
        self.subscribe = subscribe
        self.host, self.requested_port = host, port
        self.three_dir = Path(three_dir) if three_dir is not None else find_three()
        if self.three_dir is None:
            raise FileNotFoundError("three.js (npm package 'three') is not installed: run `make install`, or "
                                    "`npm install --prefix tools three`, or set FAE_THREE_DIR to its folder")
        self._head = head_message(model, skin_colors)
        self._server = None
        self._files: dict[Path, bytes] = {}  # read once: the event loop also steps the faces
        self.pages_total = 0

    @property
    def port(self) -> int:
        if self._server is None:
            raise RuntimeError("LiveView.port: not started")
        return self._server.sockets[0].getsockname()[1]

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    async def start(self) -> None:
        from websockets.asyncio.server import ServerConnection, serve

        class BoundedConnection(ServerConnection):
            def data_received(self, data: bytes) -> None:
                super().data_received(data)
                if self.transport is not None and self.transport.get_write_buffer_size() > MAX_PAGE_BUFFER:
                    self.transport.abort()  # it sends and never reads: its pongs would fill memory

        self._server = await serve(self._page, self.host, self.requested_port, process_request=self._http,
                                   max_size=2 ** 16, compression=None, logger=log, close_timeout=CLOSE_SECONDS,
                                   create_connection=BoundedConnection)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    # -- HTTP ------------------------------------------------------------------------
    def _file(self, path: str) -> Path | None:
        """The file a GET path names, only inside the page's folder or three's served ones."""
        if path in ("/", "/index.html"):
            return PAGE_DIR / "index.html"
        if path.startswith("/three/"):
            rel = path[len("/three/"):]
            for allowed in THREE_FILES:
                base = (self.three_dir / allowed).resolve()
                if rel.startswith(allowed + "/"):
                    try:
                        target = (self.three_dir / rel).resolve()
                        if target.is_file() and base in target.parents:
                            return target
                    except (OSError, ValueError):  # a NUL byte, a name too long: no such file
                        return None
        return None

    def _http(self, connection, request):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        path = request.path.split("?", 1)[0]
        if request.method not in ("GET", "HEAD"):
            return Response(HTTPStatus.METHOD_NOT_ALLOWED, "Method Not Allowed",
                            Headers([("Allow", "GET, HEAD"), ("Content-Length", "0")]), b"")
        if path == "/ws":
            return None  # the WebSocket handshake goes on
        if path == "/favicon.ico":
            return Response(HTTPStatus.NO_CONTENT, "No Content", Headers([("Content-Length", "0")]), b"")
        target = self._file(path)
        if target is None:
            return connection.respond(HTTPStatus.NOT_FOUND, f"{path}: not found\n")
        kind = "text/javascript" if target.suffix == ".js" else (mimetypes.guess_type(target.name)[0] or
                                                                 "application/octet-stream")
        body = self._files.get(target)
        if body is None:
            body = self._files[target] = target.read_bytes()
        headers = Headers([("Content-Type", f"{kind}; charset=utf-8" if kind.startswith("text") else kind),
                           ("Content-Length", str(len(body))), ("Cache-Control", "no-cache")])
        return Response(HTTPStatus.OK, "OK", headers, body if request.method == "GET" else b"")

    # -- WebSocket -------------------------------------------------------------------
    async def _page(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        self.pages_total += 1
        sub = self.subscribe(maxsize=2)  # latest frames only: a slow page skips, never slows a stream
        page = _PageQueue()
        reader = asyncio.create_task(self._drain(ws, sub, page))
        sender = None
        try:
            await ws.send(self._head)
            sender = asyncio.create_task(self._send(ws, page))
            async for event in sub:
                page.put(event)
        except ConnectionClosed:
            pass
        finally:
            sub.close()
            reader.cancel()
            if sender is not None:
                sender.cancel()

    @staticmethod
    async def _send(ws, page: "_PageQueue") -> None:
        """Send the page its streams' ends at once (each after its stream's last frame) and,
        while it holds fewer than IN_FLIGHT frames unanswered, each stream's newest frame,
        oldest stream first."""
        from websockets.exceptions import ConnectionClosed

        try:
            while True:
                await page.wake.wait()
                page.wake.clear()
                while (item := page.next_owed()) is not None:  # a stream's last frame, then its end
                    if isinstance(item, FrameEvent):
                        page.in_flight += 1
                        await ws.send(frame_message(item))
                    else:
                        await ws.send(json.dumps({"type": "end", "stream": item.stream}))
                while page.pending and page.in_flight < IN_FLIGHT:
                    event = page.pending.pop(next(iter(page.pending)))
                    page.in_flight += 1
                    await ws.send(frame_message(event))
        except ConnectionClosed:
            pass
        except Exception:  # a frame that cannot be sent: this page stops, the others go on
            log.exception("live view: a page's frames stopped")
            await ws.close()

    @staticmethod
    async def _drain(ws, sub, page: "_PageQueue") -> None:
        # the page's answers give credit for frames; reading also notices when it goes away,
        # and then its subscription ends even while no stream plays
        from websockets.exceptions import ConnectionClosed

        try:
            async for message in ws:
                if message == "ack" and page.in_flight > 0:
                    page.in_flight -= 1
                    page.wake.set()
        except ConnectionClosed:
            pass
        finally:
            sub.close()


class _PageQueue:
    """What one page is still to be sent: the newest unsent frame of each stream (the
    stream waiting longest first), and the streams' ends, each after its stream's last frame
    (sent whatever the page owes: one frame more per stream at most; at most
    MAX_OWED_END_FRAMES such frames, the newest, and MAX_OWED_ENDS ends); `in_flight`: frames
    sent, unanswered."""

    def __init__(self) -> None:
        self.pending: dict[str, FrameEvent] = {}
        self.ends: collections.deque = collections.deque()  # StreamEnd, oldest first
        # the pose each owed end is shown with first, by the end's id(), oldest first
        self.end_poses: dict[int, FrameEvent] = {}
        self.in_flight = 0
        self.wake = asyncio.Event()

    def put(self, event) -> None:
        if isinstance(event, FrameEvent):
            self.pending[event.stream] = event  # a frame not yet sent gives way to its stream's newer one
        elif isinstance(event, StreamEnd):
            last = self.pending.pop(event.stream, None)
            self.ends.append(event)
            if last is not None:  # the pose the stream ends on is shown, at once, then its end
                self.end_poses[id(event)] = last
            # a page that does not read owes more and more: its oldest ends' poses go first,
            # then the oldest ends themselves
            if len(self.end_poses) > MAX_OWED_END_FRAMES:
                del self.end_poses[next(iter(self.end_poses))]
            if len(self.ends) > MAX_OWED_ENDS:
                self.end_poses.pop(id(self.ends.popleft()), None)
        self.wake.set()

    def next_owed(self):
        """The next of what the ended streams are owed, in order (a stream's last frame, then
        its end), or None."""
        if not self.ends:
            return None
        pose = self.end_poses.pop(id(self.ends[0]), None)
        return pose if pose is not None else self.ends.popleft()
