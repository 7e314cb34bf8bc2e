"""`fae serve` end to end: a real server process with the real Player on the shipped head.

One server process is shared by the module's native and Xface tests and stopped with
SIGTERM at the end; a second one records to mp4 and is stopped with SIGINT. In process,
a lock-step client checks that served poses are exactly the Player's.
"""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fae.data import shipped_head_path
from fae.net.client import send_fap, split_fap_text
from test_net_server import DATA, expect, fap_text, n, read_all, task, xface_connect

REPO = Path(__file__).resolve().parents[1]
SHIPPED_HEAD = shipped_head_path()
START_TIMEOUT = 300.0  # a head without a stored FAP mapping is calibrated first

pytestmark = pytest.mark.slow


def run(coro, timeout: float = 120.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture(scope="module")
def head() -> Path:
    """The shipped head: package data, calibrated (test_play checks that it is)."""
    return SHIPPED_HEAD


class ServeProcess:
    """`python -m fae serve ... --port 0`, its bound port read from its stderr."""

    def __init__(self, *args: str) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, "-m", "fae", "serve", "--port", "0", *args], cwd=REPO,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                     start_new_session=True)  # a group of its own, as a terminal's job
        self.lines: list[str] = []
        self._port = threading.Event()
        self.port = 0
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        if not self._port.wait(START_TIMEOUT) or not self.port:
            self.proc.kill()
            raise AssertionError("fae serve did not start listening:\n" + "".join(self.lines))

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)
            if "listening on " in line:
                self.port = int(line.split("listening on ", 1)[1].split()[0].rsplit(":", 1)[1])
                self._port.set()
        self._port.set()

    def wait_for_line(self, pattern: str, timeout: float = 5.0) -> bool:
        """True once a line matching regex `pattern` has been written on stderr (the server
        logs what it did after doing it: a client may see a socket closed first)."""
        deadline = time.monotonic() + timeout
        while not any(re.search(pattern, line) for line in list(self.lines)):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True

    def stop(self, sig: int, timeout: float = 120.0, group: bool = False) -> tuple[int, str]:
        """Send `sig` (to its whole process group, as a terminal's Ctrl-C does, with `group`);
        (exit status, everything it wrote on stderr)."""
        if group:
            os.killpg(self.proc.pid, sig)
        else:
            self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise
        self._reader.join(10)
        return code, "".join(self.lines)


@pytest.fixture(scope="module")
def server(head):
    if not DATA.is_dir():
        pytest.skip(f"{DATA} not present")
    proc = ServeProcess("--head", str(head), "--fap-dir", str(DATA))
    yield proc
    if proc.proc.poll() is None:
        proc.proc.kill()


def test_native_client_gets_one_ack_per_frame_from_the_real_player(server):
    text = fap_text("xface_anger.fap")
    _, frames = split_fap_text(text)

    async def main():
        paced = await send_fap(text, port=server.port, rate="realtime", timeout=60)
        flood = await send_fap(text, port=server.port, rate="max", timeout=60)
        return paced, flood

    paced, flood = run(main())
    for report in (paced, flood):
        assert report.complete, report.summary()
        assert report.frames_ok == len(frames) and report.latencies.shape == (len(frames),)
        # Steps are numbered 1, 2, ... and every frame is acknowledged with the step that covered it.
        assert report.frame_steps[0] == 1 and np.all(np.diff(report.frame_steps) >= 0)
        assert set(report.frame_steps) == set(range(1, report.steps + 1))
    # Sent as fast as possible, frames pile up while the Player steps: they are coalesced.
    assert flood.steps < len(frames)


def test_bad_input_is_answered_and_the_server_goes_on_serving(server):
    text = fap_text()
    header, frames = split_fap_text(text)
    (m0, v0), (m1, v1) = frames[:2]
    payload = (f"{header}\n{m0}\n{v0}\n".encode() + bytes(range(256)) + b"\n"
               + f"{m1.replace('1', '9', 1)}\n{v1}\n{m1}\n{v1[:8]}".encode())

    async def main():
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(payload)
        writer.write_eof()
        replies = (await read_all(reader, timeout=60)).decode().splitlines()
        writer.close()
        report = await send_fap(text, port=server.port, rate="max", timeout=60)
        return replies, report

    replies, report = run(main())
    assert replies[0] == "ok header 25"
    assert f"ok {v0.split()[0]} 1" in replies
    errors = [r for r in replies if r.startswith("error ")]
    assert any("mask bit 0 or 1" in e for e in errors)
    assert errors[-1].endswith("stream ended inside a frame; expected the rest of the frame")
    assert replies[-1].startswith("done 1 frames 1 steps ")
    assert report.complete, report.summary()


def test_xface_upload_resume_stop_rewind_against_the_real_player(server):
    text = fap_text()  # 43 frames at 25 fps

    async def main():
        loop = asyncio.get_running_loop()
        reader, writer, me = await xface_connect(server.port)
        writer.write(task("UPLOAD_FAP", me, 1, text))
        assert await expect(reader, 3, timeout=60) == [n("UPLOAD_FAP", me, 1, s) for s in (1, 2, 3)]
        # The shared face is built by the first playback; build it outside the timed run.
        writer.write(task("ADVANCE_FRAME", me, 2))
        assert await expect(reader, 1) == [n("ADVANCE_FRAME", me, 2, 1)]
        writer.write(task("REWIND_PLAYBACK", me, 3))
        assert await expect(reader, 2, timeout=60) == [n("REWIND_PLAYBACK", me, 3, s) for s in (1, 3)]
        writer.write(task("RESUME_PLAYBACK", me, 4))
        assert await expect(reader, 2) == [n("RESUME_PLAYBACK", me, 4, s) for s in (1, 2)]
        t0 = loop.time()
        assert await expect(reader, 1, timeout=30) == [n("RESUME_PLAYBACK", me, 4, 3)]
        played_for = loop.time() - t0
        # At the end, RESUME has nothing left to play.
        writer.write(task("RESUME_PLAYBACK", me, 10))
        assert await expect(reader, 3) == [n("RESUME_PLAYBACK", me, 10, s) for s in (1, 2, 3)]
        # Rewind, play again and stop it half way: STOP answers 1 and 3, the RESUME never finishes.
        writer.write(task("REWIND_PLAYBACK", me, 11))
        assert await expect(reader, 2, timeout=30) == [n("REWIND_PLAYBACK", me, 11, s) for s in (1, 3)]
        writer.write(task("RESUME_PLAYBACK", me, 5))
        assert await expect(reader, 2) == [n("RESUME_PLAYBACK", me, 5, s) for s in (1, 2)]
        await asyncio.sleep(0.5)
        writer.write(task("STOP_PLAYBACK", me, 6))
        assert await expect(reader, 2, timeout=30) == [n("STOP_PLAYBACK", me, 6, s) for s in (1, 3)]
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(reader.read(1), 2.5)  # 43 frames would have ended by now
        # LOAD_FAP inside --fap-dir, then a rewind during playback restarts it from frame 0.
        writer.write(task("LOAD_FAP", me, 7, "xface_test.fap"))
        assert await expect(reader, 3, timeout=30) == [n("LOAD_FAP", me, 7, s) for s in (1, 2, 3)]
        writer.write(task("RESUME_PLAYBACK", me, 8))
        assert await expect(reader, 2) == [n("RESUME_PLAYBACK", me, 8, s) for s in (1, 2)]
        await asyncio.sleep(1.0)
        t1 = loop.time()
        writer.write(task("REWIND_PLAYBACK", me, 9))
        assert await expect(reader, 2, timeout=30) == [n("REWIND_PLAYBACK", me, 9, s) for s in (1, 3)]
        assert await expect(reader, 1, timeout=30) == [n("RESUME_PLAYBACK", me, 8, 3)]
        replayed_for = loop.time() - t1
        writer.close()
        return played_for, replayed_for

    played_for, replayed_for = run(main())
    # The stream's clock is kept even though a Player step takes about a frame period.
    assert 42 / 25 - 0.2 < played_for < 42 / 25 + 1.0
    assert 42 / 25 - 0.2 < replayed_for < 42 / 25 + 1.0


def test_sigterm_stops_the_server_cleanly(server):
    text = fap_text("xface_anger.fap")

    async def main():  # its own streams: with xdist this may be the server's first test
        return [await send_fap(text, port=server.port, rate="max", timeout=60) for _ in range(2)]

    assert all(report.complete for report in run(main()))
    code, err = server.stop(signal.SIGTERM)
    assert code == 0, err
    assert "stopped after" in err and "Traceback" not in err
    stats = err.split("native streams: ", 1)[1]
    frames, steps = int(stats.split()[0]), int(stats.split(" frames in ")[1].split()[0])
    assert frames >= 2 * 43 and 0 < steps <= frames


def test_record_holds_every_frame_sent_and_appears_on_sigint(head, tmp_path):
    import imageio_ffmpeg

    out = tmp_path / "served.mp4"
    text = fap_text()
    proc = ServeProcess("--head", str(head), "--record", str(out), "--size", "160x120")
    try:
        report = run(send_fap(text, port=proc.port, rate="realtime", timeout=60))
        assert report.complete, report.summary()
        assert not out.exists()  # written when the server stops
        # Ctrl-C in a terminal reaches the whole group: ffmpeg stopped with it, the video was lost
        code, err = proc.stop(signal.SIGINT, group=True)
    finally:
        if proc.proc.poll() is None:
            proc.proc.kill()
    assert code == 0, err
    assert "wrote 43 frames" in err
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    assert tuple(meta["size"]) == (160, 120) and meta["fps"] == 25
    images = [np.frombuffer(f, np.uint8).reshape(120, 160, 3) for f in reader]
    assert len(images) == 43
    # The face moves: some frame differs visibly from the first.
    change = max(float(np.abs(im.astype(int) - images[0].astype(int)).mean()) for im in images)
    assert change > 0.5
    assert [p.name for p in tmp_path.iterdir()] == ["served.mp4"]


def one_frame_streams(count: int) -> list[str]:
    """`count` one-frame .fap texts, frames spread over fap_streams/expressions.fap (the
    latest pose of a performance, as an Xface client uploads it)."""
    header, frames = split_fap_text((REPO / "fap_streams" / "expressions.fap").read_text())
    fps = header.split()[-2]
    picks = np.linspace(20, len(frames) - 20, count).astype(int)
    texts = []
    for k in picks:
        mask, values = frames[k]
        texts.append(f"2.1 pose {fps} 1\n{mask}\n0 {values.split(None, 1)[1]}\n")
    return texts


def test_record_keeps_the_time_of_an_xface_client_that_uploads_a_pose_each_second(head, tmp_path):
    """An Xface client uploads its latest pose about once a second and plays it: each pose
    lasts in the video until the next one arrived, so the video lasts as long as the
    performance, not one frame per upload."""
    import imageio_ffmpeg

    out = tmp_path / "xface.mp4"
    uploads = one_frame_streams(5)
    proc = ServeProcess("--head", str(head), "--record", str(out), "--size", "96x72")
    try:
        async def main():
            loop = asyncio.get_running_loop()
            reader, writer, me = await xface_connect(proc.port)
            played_at = []
            for k, text in enumerate(uploads):
                if played_at:  # one pose a second, on the client's clock
                    await asyncio.sleep(max(0.0, played_at[0] + k - loop.time()))
                writer.write(task("UPLOAD_FAP", me, 2 * k + 1, text) + task("RESUME_PLAYBACK", me, 2 * k + 2))
                got = await expect(reader, 6, timeout=60)
                assert n("RESUME_PLAYBACK", me, 2 * k + 2, 3) in got, got
                played_at.append(loop.time())
            writer.close()
            return played_at

        played_at = run(main(), timeout=180)
        code, err = proc.stop(signal.SIGINT)
    finally:
        if proc.proc.poll() is None:
            proc.proc.kill()
    assert code == 0, err
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    images = [np.frombuffer(f, np.uint8).reshape(72, 96, 3).astype(int) for f in reader]
    assert meta["fps"] == 25
    # The last pose shows for one frame; each earlier one until the next was played.
    performed = played_at[-1] - played_at[0]
    duration = len(images) / 25
    print(f"performed {performed:.2f} s, video {duration:.2f} s ({len(images)} frames)")
    assert abs(duration - (performed + 1 / 25)) < 0.25, (duration, performed)
    # The first pose is held for the first second: its frames stay (almost) the same.
    held = max(float(np.abs(im - images[0]).mean()) for im in images[1:20])
    assert held < 0.5
    change = max(float(np.abs(im - images[0]).mean()) for im in images)
    assert change > 0.5


def test_served_poses_are_the_players_own_when_the_client_waits_for_each_ack(head):
    """A client that sends one frame per ack never gets frames coalesced: every served pose
    is exactly what the Player computes stepping the same frames directly."""
    from fae.animate.player import Player, playable_head
    from fae.io.facemodel_gltf import read_facemodel
    from fae.io.frames import dense_frames
    from fae.io.fap import read_fap
    from fae.net.faces import player_face_factory
    from fae.net.hub import FrameEvent
    from fae.net.server import FapServer

    model = read_facemodel(head)
    path = DATA / "xface_test.fap"
    text = fap_text()
    header, frames = split_fap_text(text)
    frames = frames[:12]

    async def main():
        server = FapServer(player_face_factory(playable_head(model)), port=0)
        await server.start()
        sub = server.subscribe(maxsize=100)
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(f"{header}\n".encode())
        buf = b""
        while b"\n" not in buf:
            buf += await asyncio.wait_for(reader.read(4096), 60)
        assert buf == b"ok header 25\n"
        acks = []
        for mask, values in frames:
            writer.write(f"{mask}\n{values}\n".encode())
            line = await asyncio.wait_for(reader.readline(), 30)
            acks.append(line.decode().strip())
        writer.close()
        events = [await sub.get() for _ in frames]
        await server.close()
        return acks, events

    acks, events = run(main())
    assert acks == [f"ok {v.split()[0]} {k}" for k, (_, v) in enumerate(frames, 1)]
    player = Player(playable_head(model))
    direct = [player.step(f, dt=1 / 25) for f, _ in zip(dense_frames(read_fap(path)), frames)]
    assert all(isinstance(e, FrameEvent) for e in events)
    for event, skin in zip(events, direct):
        np.testing.assert_allclose(event.pose.skin_vertices, skin, rtol=0, atol=1e-9)
    moved = np.linalg.norm(direct[-1] - direct[0], axis=1).max()
    assert moved > 1e-4  # the frames do move the face (metres)


def test_ten_clients_starting_at_once_are_all_served_by_the_real_player(head):
    """Ten clients connecting and flooding at once: ten faces built and stepped on the
    server's pool together; every frame acknowledged, a clean stop. (Concurrent first steps
    of prebuilt faces, which crashed the server, are tested in test_sim_threads.)"""
    text = (REPO / "fap_streams" / "expressions.fap").read_text()
    _, frames = split_fap_text(text)
    proc = ServeProcess("--head", str(head))
    try:
        async def main():
            return await asyncio.gather(*[send_fap(text, port=proc.port, rate="max", timeout=120) for _ in range(10)])

        reports = run(main(), timeout=300)
        assert proc.proc.poll() is None, "".join(proc.lines)
        code, err = proc.stop(signal.SIGTERM)
    finally:
        if proc.proc.poll() is None:
            proc.proc.kill()
    for report in reports:
        assert report.complete and report.frames_ok == len(frames), report.summary()
    assert code == 0 and "Traceback" not in err, err


def test_every_face_shares_the_heads_static_arrays_and_has_its_own_state(head):
    """`fae serve` builds the head once (playable_head); every client's face is a Player of
    it: the same skin model, its own state."""
    from fae.animate.player import playable_head
    from fae.io.facemodel_gltf import read_facemodel
    from fae.net.faces import player_face_factory

    playable = playable_head(read_facemodel(head))
    factory = player_face_factory(playable)
    faces = [factory(), factory()]
    assert all(f.player.sim is playable.sim for f in faces)
    assert faces[0].player is not faces[1].player and faces[0].player.state is not faces[1].player.state
