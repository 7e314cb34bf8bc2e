"""`fae serve --live`: the page, three.js and the frames a page is sent (in process), and
a real browser (Debian's chromium driven by Playwright) watching a stream sent with `fae send`."""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import signal
import struct
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from fae.data import shipped_head_path
from fae.io.facemodel_gltf import read_facemodel
from fae.net.faces import Pose
from fae.net.hub import FrameEvent, FrameHub, StreamEnd
from fae.net.view import LiveView, find_three

REPO = Path(__file__).resolve().parents[1]
websockets = pytest.importorskip("websockets")


@pytest.fixture(scope="module")
def model():
    return read_facemodel(shipped_head_path())


@pytest.fixture
def three(tmp_path) -> Path:
    """A stand-in for the three npm package: the files the page asks for, and one beside them."""
    root = tmp_path / "three"
    (root / "build").mkdir(parents=True)
    (root / "build" / "three.module.js").write_text("export const REVISION = 'test';\n")
    (root / "examples" / "jsm" / "controls").mkdir(parents=True)
    (root / "examples" / "jsm" / "controls" / "OrbitControls.js").write_text("export class OrbitControls {}\n")
    (root / "package.json").write_text('{"name": "three"}')
    return root


def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.headers.get("Content-Type", ""), r.read()
    except urllib.error.HTTPError as e:
        return e.code, "", b""


def parse_frame(message: bytes) -> tuple[dict, np.ndarray]:
    n = struct.unpack("<I", message[:4])[0]
    return json.loads(message[4:4 + n]), np.frombuffer(message[4 + n:], dtype="<f4").reshape(-1, 3)


def event(model, index: int, lift: float) -> FrameEvent:
    skin = np.asarray(model.skin_vertices).copy()
    skin[:, 1] += lift
    jaw = np.eye(4)
    jaw[1, 3] = -lift
    return FrameEvent("native-1", index, index / 25.0, 25.0, Pose(skin, {"head": np.eye(4), "jaw": jaw}), index + 1)


def test_the_page_and_three_js_are_served_and_nothing_else(model, three):
    async def main():
        view = LiveView(model, FrameHub().subscribe, port=0, three_dir=three)
        await view.start()
        try:
            base = view.url
            loop = asyncio.get_running_loop()
            page = await loop.run_in_executor(None, get, base)
            js = await loop.run_in_executor(None, get, base + "three/build/three.module.js")
            addon = await loop.run_in_executor(None, get, base + "three/examples/jsm/controls/OrbitControls.js")
            outside = await loop.run_in_executor(None, get, base + "three/package.json")
            climb = await loop.run_in_executor(None, get, base + "three/build/%2e%2e/package.json")
            missing = await loop.run_in_executor(None, get, base + "nothing.html")
            return page, js, addon, outside, climb, missing
        finally:
            await view.close()

    page, js, addon, outside, climb, missing = asyncio.run(main())
    assert page[0] == 200 and page[1].startswith("text/html") and b"window.faeView" in page[2]
    assert js[0] == 200 and "javascript" in js[1] and b"REVISION" in js[2]
    assert addon[0] == 200
    assert outside[0] == 404 and climb[0] == 404 and missing[0] == 404


def test_every_page_gets_the_head_then_each_frame_and_one_leaving_disturbs_no_one(model, three):
    from websockets.asyncio.client import connect

    async def main():
        hub = FrameHub()
        view = LiveView(model, hub.subscribe, port=0, three_dir=three)
        await view.start()
        url = f"ws://127.0.0.1:{view.port}/ws"
        try:
            async with connect(url, max_size=2 ** 24) as stays:
                leaves = await connect(url, max_size=2 ** 24)
                heads = [json.loads(await stays.recv()), json.loads(await leaves.recv())]
                while hub.subscriber_count < 2:
                    await asyncio.sleep(0.01)
                await hub.publish(event(model, 0, 0.0))
                first = [parse_frame(await stays.recv()), parse_frame(await leaves.recv())]
                await leaves.close()  # a page closed mid-stream
                while hub.subscriber_count > 1:
                    await asyncio.sleep(0.01)
                await hub.publish(event(model, 1, 0.004))
                second = parse_frame(await stays.recv())
                await hub.publish(StreamEnd("native-1"))
                end = json.loads(await stays.recv())
                return heads, first, second, end, hub.subscriber_count, view.pages_total
        finally:
            await view.close()

    heads, first, second, end, subscribers, pages = asyncio.run(asyncio.wait_for(main(), 60))
    for head in heads:
        assert head["type"] == "head"
        assert len(head["skin"]["positions"]) == 3 * len(model.skin_vertices)
        assert len(head["skin"]["faces"]) == 3 * len(model.skin_faces)
        assert {p["name"] for p in head["parts"]} == set(model.parts) - {"cranium", "mandible"}
    for meta, skin in first:
        assert meta["stream"] == "native-1" and meta["index"] == 0 and meta["fps"] == 25.0
        assert np.allclose(skin, model.skin_vertices, atol=1e-6)
    meta, skin = second
    assert meta["index"] == 1 and np.allclose(skin[:, 1], np.asarray(model.skin_vertices)[:, 1] + 0.004, atol=1e-6)
    assert np.isclose(np.array(meta["bones"]["jaw"]).reshape(4, 4).T[1, 3], -0.004)  # column-major, as three.js
    assert end == {"type": "end", "stream": "native-1"}
    assert pages == 2 and subscribers == 1  # the page that left took its subscription along


@contextlib.asynccontextmanager
async def live_page(model, three):
    """(hub, page): a live view on a free port and one page connected to it, its head read
    and its subscription in place."""
    from websockets.asyncio.client import connect

    hub = FrameHub()
    view = LiveView(model, hub.subscribe, port=0, three_dir=three)
    await view.start()
    try:
        async with connect(f"ws://127.0.0.1:{view.port}/ws", max_size=2 ** 24) as page:
            await page.recv()  # the head
            while hub.subscriber_count < 1:
                await asyncio.sleep(0.01)
            yield hub, page
    finally:
        await view.close()


def test_a_slow_page_is_sent_the_latest_frame_not_a_backlog(model, three):
    """A page that had shown frame 1 while the stream reached frame 30 was sent frames 2,
    3, ... from the socket's buffers (a page drawing 10 frames a second of a 25 fps stream
    fell 4 s behind). A page answers each frame it has shown; it holds at most IN_FLIGHT
    unanswered, and the next it is sent is the latest."""
    from fae.net.view import IN_FLIGHT

    async def main():
        async with live_page(model, three) as (hub, page):
            for i in range(30):  # the page answers nothing meanwhile
                await hub.publish(event(model, i, 0.0))
                await asyncio.sleep(0.005)
            held = [parse_frame(await page.recv())[0]["index"] for _ in range(IN_FLIGHT)]
            with pytest.raises(asyncio.TimeoutError):
                await asyncio.wait_for(page.recv(), 0.5)  # nothing more until it answers
            await page.send("ack")
            after = parse_frame(await asyncio.wait_for(page.recv(), 5))[0]["index"]
            return held, after

    held, after = asyncio.run(asyncio.wait_for(main(), 60))
    assert held == list(range(IN_FLIGHT))
    assert after >= 27  # one of the latest frames, not frame 2


def test_a_page_that_answers_nothing_still_hears_ends_and_each_stream_gets_its_frames(model, three):
    """A stream's end waited behind a frame the page had no credit for (a page that stopped
    answering showed the stream as live for ever); with two streams at once, the newer
    stream's frame took the place of the other's, and a slow page saw only one stream."""

    def frame(stream: str, index: int) -> FrameEvent:
        e = event(model, index, 0.0)
        return FrameEvent(stream, index, e.time, e.fps, e.pose, e.step)

    async def main():
        async with live_page(model, three) as (hub, page):
            for i in range(10):
                await hub.publish(frame("A", i))
                await asyncio.sleep(0.002)
            await hub.publish(StreamEnd("A"))
            got = [await asyncio.wait_for(page.recv(), 5) for _ in range(4)]  # two frames, the last, the end
            for _ in range(3):
                await page.send("ack")  # shown at last
            seen = set()
            for i in range(20):  # two streams on one tick; the page answers each frame it gets
                await hub.publish(frame("B", i))
                await hub.publish(frame("C", i))
                await asyncio.sleep(0.01)
                while True:
                    try:
                        message = await asyncio.wait_for(page.recv(), 0.05)
                    except asyncio.TimeoutError:
                        break
                    seen.add(parse_frame(message)[0]["stream"])
                    await page.send("ack")
            return got, seen

    got, seen = asyncio.run(asyncio.wait_for(main(), 60))
    assert [parse_frame(m)[0]["index"] for m in got[:3]] == [0, 1, 9]  # the pose it ends on is shown
    assert json.loads(got[3]) == {"type": "end", "stream": "A"}
    assert seen == {"B", "C"}


def test_what_a_page_that_never_reads_is_owed_stays_bounded():
    """Case: a page that never read, while 3,000 streams ended, was owed every stream's last
    pose (370 MB -> 1.4 GB). It is owed the newest few poses, each before its stream's end,
    and every end (a name each)."""
    from fae.net.view import MAX_OWED_END_FRAMES, _PageQueue

    pose = Pose(np.zeros((1000, 3)), {})
    page = _PageQueue()
    for k in range(3000):
        page.put(FrameEvent(f"native-{k}", 0, 0.0, 25.0, pose, 1))
        page.put(StreamEnd(f"native-{k}"))
    owed = []
    while (item := page.next_owed()) is not None:
        owed.append(item)
    frames = [e for e in owed if isinstance(e, FrameEvent)]
    ends = [e.stream for e in owed if isinstance(e, StreamEnd)]
    assert len(ends) == 3000 and len(frames) == MAX_OWED_END_FRAMES
    newest = [f"native-{k}" for k in range(3000 - MAX_OWED_END_FRAMES, 3000)]
    assert ends[-1] == "native-2999" and [f.stream for f in frames] == newest
    for item, after in zip(owed, owed[1:]):
        if isinstance(item, FrameEvent):  # each pose right before its end
            assert isinstance(after, StreamEnd) and after.stream == item.stream
    assert not page.ends and not page.end_poses


def test_a_client_that_floods_pings_and_never_reads_is_cut_off(model, three):
    """Pings sent as fast as a socket takes them, pongs never read: the server's memory grew
    35 MB a second (1.6 GB in 36 s) and the FAP port slowed 5x."""
    import base64
    import os
    import socket

    async def main():
        view = LiveView(model, FrameHub().subscribe, port=0, three_dir=three)
        await view.start()
        try:
            loop = asyncio.get_running_loop()
            return await loop.run_in_executor(None, flood, view.port)
        finally:
            await view.close()

    def flood(port: int) -> float:
        with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
            key = base64.b64encode(os.urandom(16)).decode()
            sock.sendall(f"GET /ws HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                         f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
            ping = bytes([0x89, 0x80 | 125]) + b"\0\0\0\0" + b"p" * 125  # masked with zeros
            start = time.monotonic()
            try:
                while time.monotonic() - start < 30:
                    sock.sendall(ping * 64)
            except OSError:  # reset by the server
                return time.monotonic() - start
        return float("inf")

    import time

    assert asyncio.run(asyncio.wait_for(main(), 60)) < 20


def test_other_methods_are_refused_and_head_has_no_body(model, three):
    async def main():
        view = LiveView(model, FrameHub().subscribe, port=0, three_dir=three)
        await view.start()
        try:
            loop = asyncio.get_running_loop()

            def ask(method: str, path: str = "/"):
                request = urllib.request.Request(view.url.rstrip("/") + path, method=method, data=b"" if method == "POST" else None)
                try:
                    with urllib.request.urlopen(request, timeout=10) as r:
                        return r.status, r.headers.get("Content-Length"), r.read(), r.headers.get("Allow")
                except urllib.error.HTTPError as e:
                    return e.code, None, b"", e.headers.get("Allow")

            return [await loop.run_in_executor(None, ask, m) for m in ("HEAD", "POST", "DELETE")] + \
                [await loop.run_in_executor(None, ask, "GET", "/three/build/a%00b")]
        finally:
            await view.close()

    head, post, delete, nul = asyncio.run(asyncio.wait_for(main(), 60))
    assert head[0] == 200 and int(head[1]) > 1000 and head[2] == b""  # the page's length, no body
    assert post[0] == delete[0] == 405 and post[3] == "GET, HEAD"
    assert nul[0] == 404  # a NUL byte in the path was a 500 and a traceback in the log


def test_live_view_without_three_js_says_how_to_get_it(model, monkeypatch):
    import fae.net.view as view_module

    monkeypatch.setattr(view_module, "find_three", lambda: None)
    with pytest.raises(FileNotFoundError, match="make install"):
        LiveView(model, FrameHub().subscribe, port=0)


def browser_problem() -> str | None:
    """Why the browser tests cannot run here (None when they can)."""
    if find_three() is None:
        return "three.js is not installed (npm)"
    if shutil.which("chromium") is None:
        return "Debian's chromium is not installed"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed"
    return None


def launch_chromium(playwright):
    """Debian's chromium, headless, WebGL on the CPU (SwiftShader)."""
    return playwright.chromium.launch(executable_path=shutil.which("chromium"), headless=True,
                                      args=["--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                                            "--ignore-gpu-blocklist"])


def open_live_page(p, server, errors: list[str], ready: str):
    """(browser, page) of Chromium on `server`'s live view, once `ready` (JS) holds; page
    errors go to `errors`."""
    url = next(line.split("live view on ", 1)[1].strip() for line in server.lines if "live view on " in line)
    browser = launch_chromium(p)
    page = browser.new_page(viewport={"width": 480, "height": 480})
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_function(ready, timeout=60000)
    return browser, page


@pytest.mark.slow
@pytest.mark.skipif(browser_problem() is not None, reason=str(browser_problem()))
def test_a_browser_watches_a_stream_sent_to_the_server(tmp_path):
    from playwright.sync_api import sync_playwright

    from test_serve_e2e import ServeProcess

    server = ServeProcess("--live", "--http-port", "0")
    errors: list[str] = []
    try:
        with sync_playwright() as p:
            browser, page = open_live_page(p, server, errors, "window.faeView && window.faeView.headLoaded")
            sender = subprocess.Popen([sys.executable, "-m", "fae", "send", str(REPO / "fap_streams" / "expressions.fap"),
                                       "--port", str(server.port)], cwd=REPO,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            page.wait_for_function("window.faeView.framesReceived >= 10", timeout=120000)
            shot_a = tmp_path / "a.png"
            page.screenshot(path=str(shot_a))
            frame_a = page.evaluate("window.faeView.frame")
            page.wait_for_function(f"window.faeView.frame >= {frame_a} + 50", timeout=120000)
            shot_b = tmp_path / "b.png"
            page.screenshot(path=str(shot_b))
            state = page.evaluate("window.faeView")
            hud = page.inner_text("#hud")
            browser.close()
        assert sender.wait(120) == 0
    finally:
        code, log = server.stop(signal.SIGTERM)
    assert errors == []
    assert state["connected"] and state["framesReceived"] >= 10 and state["stream"].startswith("native")
    import re

    assert re.search(r"native-\d+  frame \d+  stream 25\.0 fps", hud) and "frames received" in hud, hud
    from PIL import Image

    a = np.asarray(Image.open(shot_a).convert("RGB"), dtype=float)
    b = np.asarray(Image.open(shot_b).convert("RGB"), dtype=float)
    face = (slice(120, 400), slice(120, 360))  # the face, below the HUD
    assert np.abs(a[face] - b[face]).mean() > 0.5  # the face moved between the shots
    assert code == 0, log


def textured(model):
    """The head with a texture: red where u is in [0.25, 0.75] (the face), blue elsewhere."""
    import copy

    out = copy.deepcopy(model)
    texture = np.zeros((64, 128, 3), np.uint8)
    texture[:] = (30, 60, 230)
    texture[:, 32:96] = (230, 30, 30)
    out.skin_texture = texture
    return out


def test_a_textured_head_is_sent_with_its_texture_and_seam(model):
    import base64
    import io

    from PIL import Image

    from fae.mesh import wrapped_seam
    from fae.net.view import head_message

    head = textured(model)
    skin = json.loads(head_message(head))["skin"]
    _, seam, _ = wrapped_seam(head.skin_faces, head.skin_uv)
    n = len(head.skin_vertices) + len(seam)
    assert len(skin["positions"]) == 3 * n and len(skin["uv"]) == 2 * n and skin["seam"] == seam.tolist()
    assert max(skin["faces"]) == n - 1
    png = base64.b64decode(skin["texture"].split(",", 1)[1])
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")), head.skin_texture)
    assert "texture" not in json.loads(head_message(model))["skin"]  # an untextured head as before
    from fae.render.renderer import skin_colors

    colors = np.asarray(json.loads(head_message(head, skin_colors(head)))["skin"]["colors"]).reshape(-1, 3)
    assert colors.shape == (n, 3)
    lining = np.asarray(head.skin_region) == head.region_names.index("mouth_cavity")
    assert colors[:len(lining)][lining].max() < 0.5 and np.median(colors[:len(lining)][~lining]) == 1.0


@pytest.mark.slow
@pytest.mark.skipif(browser_problem() is not None, reason=str(browser_problem()))
def test_a_browser_shows_a_textured_head_with_its_colours(model, tmp_path):
    from playwright.sync_api import sync_playwright

    from fae.io.facemodel_gltf import write_facemodel
    from test_serve_e2e import ServeProcess

    from PIL import Image

    head = tmp_path / "textured.glb"
    write_facemodel(textured(model), head)
    server = ServeProcess("--live", "--http-port", "0", "--head", str(head))
    errors: list[str] = []
    shot = tmp_path / "textured.png"

    def red_share() -> float:  # of the face's pixels in the latest screenshot
        face = np.asarray(Image.open(shot).convert("RGB"), dtype=float)[160:360, 160:320]
        return float((face[:, :, 0] > face[:, :, 2] + 40).mean())

    try:
        with sync_playwright() as p:
            # a few frames drawn with the texture (a fixed 500 ms after it loaded was too short
            # once, with the rest of the suite running beside it: the face still untextured),
            # and the screenshot taken again for up to 30 s until it shows them (once, under
            # the same load, the first screenshot after three such frames had no red at all)
            browser, page = open_live_page(p, server, errors,
                                           "window.faeView && window.faeView.texturedFramesDrawn >= 3")
            deadline = time.monotonic() + 30.0
            while True:
                page.screenshot(path=str(shot))
                if red_share() > 0.5 or time.monotonic() > deadline:
                    break
                page.wait_for_timeout(500)
            browser.close()
    finally:
        server.stop(signal.SIGTERM)
    assert errors == []
    assert red_share() > 0.5  # the face shows the texture's red, not the skin colour or blue
