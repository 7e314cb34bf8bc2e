"""The FAP server over real loopback sockets: native protocol, Xface protocol, bad input."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
import pytest

from fae.net import xface
from fae.net.client import send_fap, split_fap_text
from fae.net.faces import Pose
from fae.net.hub import FrameEvent, StreamEnd
from fae.net.server import FapServer, ServerLimits

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "fap"
TIMEOUT = 10.0


def fap_text(name: str = "xface_test.fap") -> str:
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"{path} not present")
    return path.read_text()


class LinearFace:
    """A face whose skin moves linearly with the FAP values (rest + values @ basis)."""

    rest = np.random.default_rng(7).normal(size=(40, 3)) * 0.05
    basis = np.random.default_rng(8).normal(size=(68, 120)) * 1e-6

    def __init__(self) -> None:
        self.steps = 0

    def step(self, frame, dt: float) -> Pose:
        assert dt > 0
        self.steps += 1
        return Pose(self.rest + (frame.values @ self.basis).reshape(-1, 3), {})

    def reset(self) -> None:
        self.steps = 0

    @classmethod
    def expected(cls, values: np.ndarray) -> np.ndarray:
        return cls.rest + (values @ cls.basis).reshape(-1, 3)


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


async def started(factory=LinearFace, **kwargs) -> FapServer:
    server = FapServer(factory, port=0, **kwargs)
    await server.start()
    return server


async def read_until(reader: asyncio.StreamReader, marker: bytes, timeout: float = TIMEOUT) -> bytes:
    buf = b""
    while marker not in buf:
        chunk = await asyncio.wait_for(reader.read(65536), timeout)
        if not chunk:
            break
        buf += chunk
    return buf


async def read_all(reader: asyncio.StreamReader, timeout: float = TIMEOUT) -> bytes:
    buf = b""
    while chunk := await asyncio.wait_for(reader.read(65536), timeout):
        buf += chunk
    return buf


async def native_exchange(port: int, payload: bytes) -> list[str]:
    """Send `payload`, half-close, return the server's reply lines (it closes when done)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(payload)
    await writer.drain()
    writer.write_eof()
    data = await read_all(reader)
    writer.close()
    return data.decode().splitlines()


def replies_by_kind(lines: list[str]) -> tuple[list[str], list[str], list[str]]:
    """(frame numbers acknowledged in order, error lines in order, other lines)."""
    oks, errors, other = [], [], []
    for line in lines:
        if line.startswith("ok ") and not line.startswith("ok header"):
            number, step = line.split()[1:]
            assert int(step) >= 1, line
            oks.append(number)
        elif line.startswith("error "):
            errors.append(line)
        else:
            other.append(line)
    return oks, errors, other


async def well_behaved(port: int) -> None:
    report = await send_fap(fap_text(), port=port)
    assert report.complete, report.summary()


# -- native protocol ---------------------------------------------------------------

def test_native_stream_acks_every_frame_and_publishes_its_pose():
    text = fap_text()
    header, frames = split_fap_text(text)

    async def main():
        server = await started()
        sub = server.subscribe(maxsize=1000)
        replies = await native_exchange(server.port, text.encode())
        events = []
        while not sub._queue.empty():
            events.append(await sub.get())
        await server.close()
        return replies, events

    replies, events = run(main())
    numbers = [values.split()[0] for _, values in frames]
    oks, errors, other = replies_by_kind(replies)
    assert replies[0] == "ok header 25" and oks == numbers and errors == []
    steps = sorted({int(line.split()[2]) for line in replies[1:-1]})
    assert steps == list(range(1, len(steps) + 1))
    assert replies[-1] == f"done 43 frames {len(steps)} steps 0 errors"
    poses = [e for e in events if isinstance(e, FrameEvent)]
    assert [str(e.index) for e in poses] == numbers
    assert [e.step for e in poses] == [int(line.split()[2]) for line in replies[1:-1]]
    assert isinstance(events[-1], StreamEnd)
    # The pose of the last frame is the face at the held values of the whole stream.
    held = np.zeros(68)
    for mask, values in frames:
        bits = np.array(mask.split(), dtype=int).astype(bool)
        held[bits] = np.array(values.split()[1:], dtype=float)
    np.testing.assert_allclose(poses[-1].pose.skin_vertices, LinearFace.expected(held), atol=1e-12)


def test_send_client_reports_latency_and_rate():
    async def main():
        server = await started()
        report = await send_fap(fap_text(), port=server.port, rate="max")
        await server.close()
        return report

    report = run(main())
    assert report.complete and report.frames_ok == 43
    assert report.latencies.shape == (43,) and np.all(report.latencies > 0)
    assert report.latency_ms(50) <= report.latency_ms(99)
    assert report.frames_per_second > 0


def test_several_clients_each_get_their_own_stream_and_face():
    text = fap_text()

    async def main():
        faces = []

        def factory():
            faces.append(LinearFace())
            return faces[-1]

        server = await started(factory)
        reports = await asyncio.gather(*[send_fap(text, port=server.port) for _ in range(6)])
        await server.close()
        return reports, faces

    reports, faces = run(main())
    assert all(r.complete and r.frames_ok == 43 for r in reports)
    assert len(faces) == 6 and all(1 <= f.steps <= 43 for f in faces)
    assert sorted(f.steps for f in faces) == sorted(r.steps for r in reports)


def test_silent_native_client_gets_the_greeting_and_can_still_stream():
    text = fap_text()

    async def main():
        server = await started(limits=ServerLimits(greeting_delay=0.05))
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        greeting = await read_until(reader, b"\0\0")
        writer.write(text.encode())
        writer.write_eof()
        rest = await read_all(reader)
        writer.close()
        await server.close()
        return greeting, rest.decode().splitlines()

    greeting, lines = run(main())
    assert greeting == b'<notify name="CONNECTION_OK" ownerId="1" taskId="0" status="0"/>\0\0'
    oks, errors, other = replies_by_kind(lines)
    assert lines[0] == "ok header 25" and len(oks) == 43 and not errors
    assert other[-1].startswith("done 43 frames")


# -- bad input -----------------------------------------------------------------------

def _first_frame(text: str) -> tuple[str, str, str]:
    header, frames = split_fap_text(text)
    return header, frames[0][0], frames[0][1]


def test_malformed_lines_get_an_error_naming_the_line_and_the_stream_goes_on():
    text = fap_text()
    header, frames = split_fap_text(text)
    (m0, v0), (m1, v1), (m2, v2) = frames[:3]
    payload = "\n".join([header, m0, v0,
                         m1.replace("1", "7", 1), v1,   # bad mask: one error, its values line is skipped
                         m2, v2 + " 99",               # one value too many
                         *frames[3]]) + "\n"

    async def main():
        server = await started()
        replies = await native_exchange(server.port, payload.encode())
        await well_behaved(server.port)
        await server.close()
        return replies

    replies = run(main())
    oks, errors, other = replies_by_kind(replies)
    assert replies[0] == "ok header 25"
    assert oks == [v0.split()[0], frames[3][1].split()[0]]
    assert len(errors) == 2
    assert errors[0].startswith("error 4: ") and "mask bit 0 or 1" in errors[0]
    assert errors[1].startswith("error 7: ") and "values after the frame number" in errors[1]
    assert other[-1].startswith("done 2 frames") and other[-1].endswith(" 2 errors")


def test_bad_header_binary_garbage_and_oversized_lines_are_answered_and_others_still_served():
    header, mask, values = _first_frame(fap_text())

    async def main():
        server = await started(limits=ServerLimits(max_line=2048))
        bad_header = await native_exchange(server.port, b"hello there\n" + f"{header}\n{mask}\n{values}\n".encode())
        garbage = await native_exchange(server.port, f"{header}\n".encode() + bytes(range(256)) * 3 + b"\n"
                                        + f"{mask}\n{values}\n".encode())
        oversized = await native_exchange(server.port, f"{header}\n".encode() + b"1 " * 100_000 + b"\n"
                                          + f"{mask}\n{values}\n".encode())
        await well_behaved(server.port)
        await server.close()
        return bad_header, garbage, oversized

    bad_header, garbage, oversized = run(main())
    number = values.split()[0]
    assert bad_header[0].startswith("error 1: ") and "version" in bad_header[0]
    assert bad_header[1:] == ["ok header 25", f"ok {number} 1", "done 1 frames 1 steps 1 errors"]
    oks, errors, other = replies_by_kind(garbage)
    assert garbage[0] == "ok header 25" and oks == [number]
    assert errors and all("expected" in e for e in errors)
    assert oversized == ["ok header 25", "error 2: expected a line of at most 2048 bytes", f"ok {number} 1",
                         "done 1 frames 1 steps 1 errors"]


def test_partial_frame_at_disconnect_is_reported():
    header, mask, values = _first_frame(fap_text())

    async def main():
        server = await started()
        cut_after_mask = await native_exchange(server.port, f"{header}\n{mask}\n".encode())
        cut_mid_line = await native_exchange(server.port, f"{header}\n{mask}\n{values[:10]}".encode())
        await well_behaved(server.port)
        await server.close()
        return cut_after_mask, cut_mid_line

    cut_after_mask, cut_mid_line = run(main())
    assert cut_after_mask == ["ok header 25", "error 3: stream ended inside a frame; expected the rest of the frame",
                              "done 0 frames 0 steps 1 errors"]
    assert cut_mid_line[-2:] == ["error 3: stream ended inside a frame; expected the rest of the frame",
                                 "done 0 frames 0 steps 1 errors"]


def test_every_half_close_is_answered_with_done_even_without_a_header():
    """Blank and comment lines only, or a bad header, then EOF: the client was closed without
    the `done` line the protocol promises after every half-close."""
    async def main():
        server = await started()
        comments = await native_exchange(server.port, b"\n# nothing yet\n\n")
        bad_header = await native_exchange(server.port, b"hello\n")
        await well_behaved(server.port)
        await server.close()
        return comments, bad_header

    comments, bad_header = run(main())
    assert comments == ["done 0 frames 0 steps 0 errors"]
    assert bad_header[-1] == "done 0 frames 0 steps 1 errors" and bad_header[0].startswith("error 1: ")


def test_a_client_that_keeps_sending_garbage_is_closed_after_max_errors():
    async def main():
        server = await started(limits=ServerLimits(max_errors=5))
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(b"2.1 flood 25 10\n" + b"x y z\n" * 10_000)
        await writer.drain()
        data = await read_all(reader)  # the server closes: read ends
        writer.close()
        await well_behaved(server.port)
        await server.close()
        return data.decode().splitlines()

    lines = run(main())
    assert lines[0] == "ok header 25"
    assert len(lines) == 6 and lines[-1].endswith("(error 5: closing)")


def test_abrupt_disconnect_mid_frame_and_a_client_that_never_reads_do_not_stall_others():
    text = fap_text("xface_anger.fap")
    header, frames = split_fap_text(text)
    body = "".join(f"{m}\n{v}\n" for m, v in frames)

    async def main():
        server = await started(limits=ServerLimits(window=4, max_output=4096))
        # A client that floods frames and never reads its acks.
        _, hog = await asyncio.open_connection("127.0.0.1", server.port)
        hog.write((header + "\n" + body).encode())
        # A client that vanishes in the middle of a line.
        _, gone = await asyncio.open_connection("127.0.0.1", server.port)
        gone.write((header + "\n" + frames[0][0] + "\n" + frames[0][1][:5]).encode())
        await gone.drain()
        gone.transport.abort()
        await asyncio.wait_for(well_behaved(server.port), TIMEOUT)
        hog.transport.abort()
        await asyncio.wait_for(well_behaved(server.port), TIMEOUT)
        await server.close()

    run(main())


def test_a_face_that_fails_to_build_is_reported_and_the_server_keeps_serving():
    calls = []

    def factory():
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("no head here")
        return LinearFace()

    async def main():
        server = await started(factory)
        replies = await native_exchange(server.port, fap_text().encode())
        await well_behaved(server.port)
        await server.close()
        return replies

    replies = run(main())
    assert replies[0].startswith("error 1: the server could not build a face") and "no head here" in replies[0]


# -- Xface protocol ------------------------------------------------------------------

def task(name: str, owner: int, task_id: int, *params: str, end: bytes = b"\0") -> bytes:
    body = "".join(f"<param>{p}</param>" for p in params)
    return f'<task name="{name}" ownerId="{owner}" taskId="{task_id}">{body}</task>'.encode() + end


def notifies(data: bytes) -> list[str]:
    assert data.endswith(b"\0\0"), data[-40:]
    parts = data.split(b"\0\0")[:-1]
    return [p.decode() for p in parts]


def n(name: str, owner: int, task_id: int, status: int) -> str:
    return f'<notify name="{name}" ownerId="{owner}" taskId="{task_id}" status="{status}"/>'


async def xface_connect(port: int):
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    greeting = await read_until(reader, b"\0\0")
    owner = int(greeting.split(b'ownerId="')[1].split(b'"')[0])
    assert greeting == n("CONNECTION_OK", owner, 0, 0).encode() + b"\0\0"
    return reader, writer, owner


async def expect(reader: asyncio.StreamReader, count: int, timeout: float = TIMEOUT) -> list[str]:
    buf = b""
    while buf.count(b"\0\0") < count:
        chunk = await asyncio.wait_for(reader.read(65536), timeout)
        assert chunk, f"connection closed after {buf!r}"
        buf += chunk
    return notifies(buf)


def test_xface_upload_resume_stop_rewind_with_exact_notify_bytes():
    text = fap_text()  # 43 frames at 25 fps

    async def main():
        server = await started(limits=ServerLimits(greeting_delay=0.05))
        sub = server.subscribe(maxsize=1000)
        reader, writer, me = await xface_connect(server.port)
        # Two tasks in one write, one ended by two NULs, the other by nothing.
        writer.write(task("UPLOAD_FAP", me, 1, text, end=b"\0\0") + task("RESUME_PLAYBACK", me, 2, end=b""))
        got = await expect(reader, 5)
        # The session acks each task at once; the shared queue reports progress: order across the two varies.
        assert sorted(got) == sorted([n("UPLOAD_FAP", me, 1, 1), n("UPLOAD_FAP", me, 1, 2), n("UPLOAD_FAP", me, 1, 3),
                                      n("RESUME_PLAYBACK", me, 2, 1), n("RESUME_PLAYBACK", me, 2, 2)])
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        assert await expect(reader, 1, timeout=5) == [n("RESUME_PLAYBACK", me, 2, 3)]
        played_for = loop.time() - t0
        frames = []
        while not sub._queue.empty():
            frames.append(await sub.get())
        # Rewind, play again, stop mid-playback: no 3 for that RESUME; STOP answers 1 then 3.
        writer.write(task("REWIND_PLAYBACK", me, 3))
        assert await expect(reader, 2) == [n("REWIND_PLAYBACK", me, 3, 1), n("REWIND_PLAYBACK", me, 3, 3)]
        writer.write(task("RESUME_PLAYBACK", me, 4))
        assert await expect(reader, 2) == [n("RESUME_PLAYBACK", me, 4, 1), n("RESUME_PLAYBACK", me, 4, 2)]
        await asyncio.sleep(0.2)
        writer.write(task("STOP_PLAYBACK", me, 5))
        assert await expect(reader, 2) == [n("STOP_PLAYBACK", me, 5, 1), n("STOP_PLAYBACK", me, 5, 3)]
        after_stop = []
        while not sub._queue.empty():
            after_stop.append(await sub.get())
        # Nothing else arrives (the interrupted RESUME never finishes).
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(reader.read(1), 0.3)
        writer.close()
        await server.close()
        return frames, played_for, after_stop

    frames, played_for, after_stop = run(main())
    # The second playback got a few frames in before STOP; STOP shows frame 0 again and ends the stream.
    replay = [e.index for e in after_stop if isinstance(e, FrameEvent)]
    assert 2 <= len(replay) < 43 and replay[:-1] == list(range(len(replay) - 1)) and replay[-1] == 0
    assert isinstance(after_stop[-1], StreamEnd)
    poses = [e for e in frames if isinstance(e, FrameEvent)]
    assert [e.index for e in poses] == list(range(43)) and isinstance(frames[-1], StreamEnd)
    assert 42 / 25 - 0.25 < played_for < 42 / 25 + 1.0  # played at the stream's 25 fps


def test_xface_errors_unknown_task_garbage_missing_stream_and_bad_fap():
    async def main():
        server = await started(limits=ServerLimits(greeting_delay=0.05))
        reader, writer, me = await xface_connect(server.port)
        writer.write(task("PAUSE_PLAYBACK", me, 1))
        assert await expect(reader, 1) == [n("ERROR", 0, 0, 7)]
        writer.write(b"<task name='x' ownerId='1'\0")
        assert await expect(reader, 1) == [n("ERROR", 0, 0, 7)]
        writer.write(task("RESUME_PLAYBACK", me, 2))  # nothing loaded
        assert await expect(reader, 2) == [n("RESUME_PLAYBACK", me, 2, 1), n("RESUME_PLAYBACK", me, 2, 7)]
        writer.write(task("UPLOAD_FAP", me, 3, "2.1 bad 25 1\n0 1\n5 5\n"))
        assert await expect(reader, 4) == [n("UPLOAD_FAP", me, 3, 1), n("UPLOAD_FAP", me, 3, 2),
                                           n("UPLOAD_FAP", me, 3, 7), n("UPLOAD_FAP", me, 3, 3)]
        # a stream without frames: refused like bad text (it was finished, 3, and playing it found nothing)
        writer.write(task("UPLOAD_FAP", me, 6, "2.1 x 25 5\n"))
        assert await expect(reader, 4) == [n("UPLOAD_FAP", me, 6, 1), n("UPLOAD_FAP", me, 6, 2),
                                           n("UPLOAD_FAP", me, 6, 7), n("UPLOAD_FAP", me, 6, 3)]
        writer.write(task("LOAD_FAP", me, 4, "/etc/passwd"))  # no --fap-dir: refused
        assert await expect(reader, 3) == [n("LOAD_FAP", me, 4, 1), n("LOAD_FAP", me, 4, 2), n("LOAD_FAP", me, 4, 7)]
        writer.write(task("UPLOAD_FAP", 0, 5, fap_text()))  # ownerId 0: only the queued ack
        assert await expect(reader, 1) == [n("UPLOAD_FAP", 0, 5, 1)]
        writer.close()
        await well_behaved(server.port)
        await server.close()

    run(main())


def test_xface_load_fap_reads_only_inside_fap_dir(tmp_path):
    (tmp_path / "a.fap").write_text(fap_text())
    (tmp_path / "notes.txt").write_text("2.1 x 25 0\n")

    async def main():
        server = await started(fap_dir=tmp_path, limits=ServerLimits(greeting_delay=0.05))
        reader, writer, me = await xface_connect(server.port)
        results = {}
        for i, path in enumerate(["a.fap", str(tmp_path / "a.fap"), "../a.fap", "notes.txt", "missing.fap"], 1):
            writer.write(task("LOAD_FAP", me, i, path))
            got = await expect(reader, 3)
            results[path] = got[-1]
        writer.close()
        await server.close()
        return results, me

    results, me = run(main())
    assert results["a.fap"].endswith('status="3"/>')
    assert results[str(tmp_path / "a.fap")].endswith('status="3"/>')
    for bad in ("../a.fap", "notes.txt", "missing.fap"):
        assert results[bad].endswith('status="7"/>'), bad


def test_an_xface_task_naming_a_native_clients_id_does_not_reach_it():
    """Case: an Xface client sent REWIND_PLAYBACK with a native client's id as its ownerId,
    and the native client found `<notify ...>` among its replies (`fae send` gave up, exit 2).
    Notifications go to Xface clients only."""
    text = fap_text().encode()

    async def main():
        server = await started(LinearFace, limits=ServerLimits(greeting_delay=0.05))
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        header, body = text.split(b"\n", 1)
        writer.write(header + b"\n")
        await writer.drain()
        assert (await asyncio.wait_for(reader.readline(), TIMEOUT)).startswith(b"ok header")
        r, w, owner = await xface_connect(server.port)
        native_id = owner - 1
        w.write(task("REWIND_PLAYBACK", native_id, 2))
        assert await expect(r, 1) == [n("REWIND_PLAYBACK", native_id, 2, 1)]  # queued: its own ack
        await asyncio.sleep(0.2)  # the task done: its later notifications had gone to the native client
        writer.write(body)
        await writer.drain()
        writer.write_eof()
        rest = (await read_all(reader)).decode()
        w.close()
        writer.close()
        await server.close()
        return rest

    rest = run(main())
    assert "<notify" not in rest and "\0" not in rest
    oks, errors, _ = replies_by_kind(rest.splitlines())
    assert oks and not errors


def test_xface_notifications_are_routed_by_owner_id_and_clients_share_one_face():
    text = fap_text()

    async def main():
        built = []

        def factory():
            built.append(LinearFace())
            return built[-1]

        server = await started(factory, limits=ServerLimits(greeting_delay=0.05))
        r1, w1, id1 = await xface_connect(server.port)
        r2, w2, id2 = await xface_connect(server.port)
        assert id2 == id1 + 1
        # Client 1 uploads on behalf of client 2: client 1 gets the queued ack, client 2 the rest.
        w1.write(task("UPLOAD_FAP", id2, 9, text))
        assert await expect(r1, 1) == [n("UPLOAD_FAP", id2, 9, 1)]
        assert await expect(r2, 2) == [n("UPLOAD_FAP", id2, 9, 2), n("UPLOAD_FAP", id2, 9, 3)]
        w1.write(task("ADVANCE_FRAME", id1, 10))
        w2.write(task("ADVANCE_FRAME", id2, 11))
        assert await expect(r1, 1) == [n("ADVANCE_FRAME", id1, 10, 1)]
        assert await expect(r2, 1) == [n("ADVANCE_FRAME", id2, 11, 1)]
        await asyncio.sleep(0.1)
        w1.close()
        w2.close()
        await server.close()
        return built

    built = run(main())
    assert len(built) == 1 and built[0].steps == 2


def test_xface_oversized_task_closes_only_that_client():
    async def main():
        server = await started(limits=ServerLimits(greeting_delay=0.05, max_task=4096))
        reader, writer, me = await xface_connect(server.port)
        writer.write(b"<task name=\"UPLOAD_FAP\" ownerId=\"1\" taskId=\"1\"><param>" + b"0 " * 10_000)
        data = await read_all(reader)
        writer.close()
        await well_behaved(server.port)
        await server.close()
        return data

    assert notifies(run(main())) == [n("ERROR", 0, 0, 7)]


# -- codecs --------------------------------------------------------------------------

def fed_in_pieces(splitter: xface.TaskSplitter, stream: bytes, size: int) -> list[xface.XfaceTask]:
    """The tasks `splitter` finds in `stream` fed `size` bytes at a time."""
    got = []
    for i in range(0, len(stream), size):
        got += splitter.feed(stream[i:i + size])
    return [xface.parse_task(m) for m in got]


def test_task_splitter_finds_tasks_across_reads_and_terminators():
    splitter = xface.TaskSplitter()
    stream = task("A", 1, 1, end=b"") + task("B", 1, 2, end=b"\0\0") + task("C", 1, 3, "x\ny", end=b"\0")
    tasks = fed_in_pieces(splitter, stream, 7)
    assert [(t.name, t.task_id, t.params) for t in tasks] == [("A", 1, ()), ("B", 2, ()), ("C", 3, ("x\ny",))]
    assert splitter.buffered == 0
    # a self-closing task with nothing after it was never answered, and the next task's bytes
    # were read as junk after it (both lost); a quoted `>` or `/>` does not end a start tag
    stream = (b'<task name="D" ownerId="1" taskId="4"/>' + task("E", 1, 5, end=b"")
              + b'<task name="F" ownerId="1" taskId="6" note="a/>b">' + b"<param>1</param></task>")
    tasks = fed_in_pieces(splitter, stream, 5)
    assert [(t.name, t.task_id, t.params) for t in tasks] == [("D", 4, ()), ("E", 5, ()), ("F", 6, ("1",))]
    assert splitter.buffered == 0


# -- the `fae send` command ------------------------------------------------------------

def test_fae_send_reports_and_exits_nonzero_when_frames_are_rejected(tmp_path, capsys):
    from fae.cli import main as fae_main

    good = DATA / "xface_test.fap"
    fap_text()
    header, frames = split_fap_text(good.read_text())
    bad = tmp_path / "bad.fap"
    bad.write_text("\n".join([header, frames[0][0], frames[0][1] + " 1 2 3", *frames[1]]) + "\n")

    async def main():
        server = await started()
        ok = await asyncio.to_thread(fae_main, ["send", str(good), "--port", str(server.port), "--rate", "max"])
        rejected = await asyncio.to_thread(fae_main, ["send", str(bad), "--port", str(server.port)])
        await server.close()
        refused = await asyncio.to_thread(fae_main, ["send", str(good), "--port", str(server.port)])
        return ok, rejected, refused

    ok, rejected, refused = run(main())
    out, err = capsys.readouterr()
    assert (ok, rejected, refused) == (0, 1, 2)
    assert "43/43 frames ok in " in out and ", 0 errors" in out and "latency p50" in out
    assert "1/2 frames ok in 1 face steps, 1 errors" in out
    assert "server: error 3:" in err


def test_fae_send_shows_why_a_server_closed_on_its_errors(tmp_path, capsys):
    """At the default real-time rate, a stream whose every frame the server refuses: the
    server closes after its 32nd error, and `fae send` said only "Transport endpoint is not
    connected" (exit 2), its 32 reasons lost."""
    from fae.cli import main as fae_main

    mask = " ".join(["0", "0", "1", "1", "1"] + ["0"] * 63)  # jaw and two lip FAPs: each frame needs 3 values
    bad = tmp_path / "bad40.fap"
    bad.write_text("2.1 bad 100 40\n" + "".join(f"{mask}\n{k} 1\n" for k in range(40)))

    async def main():
        server = await started()
        code = await asyncio.to_thread(fae_main, ["send", str(bad), "--port", str(server.port)])
        await server.close()
        return code

    code = run(main())
    out, err = capsys.readouterr()
    assert code == 1, err
    assert "server: error 3: expected 3 values" in err and "not connected" not in err


# -- audio tasks, coalescing, spare faces, the parser's partial frames ------------------

def test_upload_wav_bytes_are_passed_over_and_wav_tasks_are_refused():
    text = fap_text()
    # Raw audio that looks like tasks and terminators: none of it may be read as a task.
    audio = b"RIFF" + b"\0\0" + task("KILL_APP", 1, 99) + b"</task>\0" + bytes(range(256)) * 4

    async def main():
        server = await started(limits=ServerLimits(greeting_delay=0.05))
        reader, writer, me = await xface_connect(server.port)
        writer.write(task("UPLOAD_WAV", me, 1, "speech.wav", str(len(audio))) + audio[:100])
        await writer.drain()
        await asyncio.sleep(0.05)  # the rest of the audio in a later read
        writer.write(audio[100:] + task("UPLOAD_FAP", me, 2, text))
        got = await expect(reader, 4)
        writer.write(task("LOAD_WAV", me, 3, "speech.wav"))
        got += await expect(reader, 1)
        writer.write(task("UPLOAD_WAV", me, 4, "speech.wav", "lots"))  # no byte count: cannot go on
        got += await expect(reader, 1)
        rest = await read_all(reader)
        writer.close()
        await well_behaved(server.port)
        await server.close()
        return got, rest

    got, rest = run(main())
    assert got == [n("ERROR", 0, 0, 7), *[n("UPLOAD_FAP", 1, 2, s) for s in (1, 2, 3)], n("ERROR", 0, 0, 7),
                   n("ERROR", 0, 0, 7)]
    assert rest == b""  # closed


def test_frames_arriving_while_the_face_steps_are_coalesced_and_errors_answered_at_once():
    """A face slower than the client: every frame is acknowledged, frames that arrived during
    a step share the next step, which plays the latest held values; a bad line is answered
    before the acks of the frames still waiting for the face."""
    text = fap_text()
    header, frames = split_fap_text(text)
    steps_dt = []

    class SlowFace(LinearFace):
        def step(self, frame, dt):
            steps_dt.append(dt)
            import time
            time.sleep(0.05)
            return super().step(frame, dt)

    bad = [(frames[5][0].replace("0", "x", 1), frames[5][1])]
    body = frames[:5] + bad + frames[6:]
    payload = (header + "\n" + "".join(f"{m}\n{v}\n" for m, v in body)).encode()

    async def main():
        server = await started(SlowFace)
        sub = server.subscribe(maxsize=1000)
        replies = await native_exchange(server.port, payload)
        events = []
        while not sub._queue.empty():
            events.append(await sub.get())
        stats = server.stats()
        await server.close()
        return replies, events, stats

    replies, events, stats = run(main())
    oks, errors, other = replies_by_kind(replies)
    numbers = [v.split()[0] for _, v in frames]
    assert oks == numbers[:5] + numbers[6:] and len(errors) == 1 and "mask bit" in errors[0]
    # The error came back before the last frames' acks (they waited for the face).
    assert replies.index(errors[0]) < replies.index(f"ok {numbers[-1]} {replies[-2].split()[2]}")
    poses = [e for e in events if isinstance(e, FrameEvent)]
    steps = [e.step for e in poses]
    assert steps[-1] == len(steps_dt) < len(poses) and steps == sorted(steps)
    assert stats["native_frames"] == len(poses) and stats["native_steps"] == steps[-1]
    assert replies[-1] == f"done {len(poses)} frames {steps[-1]} steps 1 errors"
    # Each step plays one frame period with the values held after its latest frame.
    assert all(dt == pytest.approx(1 / 25) for dt in steps_dt)
    held = np.zeros(68)
    for mask, values in frames[:5] + frames[6:]:
        bits = np.array(mask.split(), dtype=int).astype(bool)
        held[bits] = np.array(values.split()[1:], dtype=float)
    np.testing.assert_allclose(poses[-1].pose.skin_vertices, LinearFace.expected(held), atol=1e-12)
    for a, b in zip(poses, poses[1:]):
        assert (a.pose is b.pose) == (a.step == b.step)


def test_spare_faces_are_built_ahead_and_each_client_gets_its_own():
    text = fap_text()
    built = []

    def factory():
        built.append(LinearFace())
        return built[-1]

    async def main():
        server = await started(factory, spare_faces=1)
        await asyncio.sleep(0.2)
        assert len(built) == 1  # built before any client came
        first = await send_fap(text, port=server.port)
        second = await send_fap(text, port=server.port)
        await server.close()
        return first, second

    first, second = run(main())
    assert first.complete and second.complete
    assert len(built) == 3 and [f.steps for f in built[:2]] == [first.steps, second.steps]


def test_parser_discards_a_partial_frame_and_reads_the_next_line_as_a_mask():
    from fae.io.fap import FapFormatError, FapParser

    header, frames = split_fap_text(fap_text())
    (m0, v0), (m1, v1) = frames[:2]
    parser = FapParser("socket")
    parser.feed_line(header, 1)
    assert parser.discard_partial_frame() is False
    parser.feed_line(m0, 2)
    assert parser.in_frame
    assert parser.discard_partial_frame() is True and not parser.in_frame
    with pytest.raises(FapFormatError, match="mask bit"):
        parser.feed_line(v0, 3)  # now read as a mask line: a values line is not one
    parser.feed_line(m1, 4)
    frame = parser.feed_line(v1, 5)
    assert frame is not None and str(frame.number) == v1.split()[0]


def test_a_face_is_never_stepped_by_two_pool_threads_even_when_a_waiter_gives_up():
    """Faces share one pool of threads. A caller that stops waiting for a step (Xface's
    STOP_PLAYBACK cancels a step in flight, then resets) must not let the face's next job
    start while that step still runs."""
    import threading
    import time

    from fae.net.faces import FacePool

    running, overlaps = [0], []
    lock = threading.Lock()

    class SlowFace:
        def _enter(self):
            with lock:
                running[0] += 1
                overlaps.append(running[0] > 1)
            time.sleep(0.05)
            with lock:
                running[0] -= 1

        def step(self, frame, dt):
            self._enter()
            return Pose(np.zeros((1, 3)), {})

        def reset(self):
            self._enter()

    async def main():
        pool = FacePool(SlowFace, threads=4)
        worker = pool.take()
        await worker.ready()
        first = worker.submit(None, 0.04)
        queued = worker.submit(None, 0.04)
        await asyncio.sleep(0.01)
        first.cancel()   # the waiter gives up while the step runs
        queued.cancel()  # and on one still queued
        await worker.reset()
        await worker.submit(None, 0.04)
        worker.close()
        pool.close()

    asyncio.run(main())
    assert len(overlaps) >= 3 and not any(overlaps)


# -- limits on connections -------------------------------------------------------------

def test_silent_sockets_make_room_for_a_newcomer_and_are_closed_when_idle():
    limits = ServerLimits(max_clients=4, max_per_address=3, idle_timeout=1.0, evict_idle=0.2)

    async def closed(reader) -> bool:
        try:
            while await asyncio.wait_for(reader.read(65536), 5):
                pass
        except asyncio.TimeoutError:
            return False
        except ConnectionError:  # the one that made room was reset
            pass
        return True

    async def main():
        server = await started(limits=limits)
        try:
            horde = [await asyncio.open_connection("127.0.0.1", server.port) for _ in range(10)]
            await asyncio.sleep(0.3)
            assert len(server.clients) == 3  # one address's share
            await well_behaved(server.port)  # the same address: takes the idlest one's place
            assert all(await asyncio.gather(*(closed(r) for r, _ in horde)))  # idle timeout
            assert server.clients == {}
            for _, w in horde:
                w.close()
        finally:
            await server.close()

    run(main())


def test_an_xface_client_waiting_for_its_playback_is_not_idle():
    """A client silent while the stream it started plays is waiting, not idle."""
    text = fap_text()  # 43 frames at 25 fps: 1.7 s, longer than the idle timeout

    async def main():
        server = await started(limits=ServerLimits(idle_timeout=0.5))
        try:
            reader, writer, owner = await xface_connect(server.port)
            writer.write(task("UPLOAD_FAP", owner, 1, text) + task("RESUME_PLAYBACK", owner, 2))
            got = await expect(reader, 6, timeout=10)
            assert got[-1] == n("RESUME_PLAYBACK", owner, 2, 3)  # finished, after 1.7 s of silence
            assert await asyncio.wait_for(reader.read(65536), 5) == b""  # then idle: closed
            writer.close()
        finally:
            await server.close()

    run(main())


def test_an_uploaded_stream_keeps_only_the_frames_it_sent():
    from fae.net.decode import decode_text

    mask = " ".join(["0", "0", "1"] + ["0"] * 65)
    fps, frames = decode_text(f"2.1 gap 25 2\n{mask}\n0 100\n{mask}\n{10 ** 12} 900\n", "upload")
    assert fps == 25 and len(frames) == 10 ** 12 + 1 and frames.sent == 2
    held = frames[123_456_789]
    assert held.index == 123_456_789 and held.time == 123_456_789 / 25 and held.values[2] == 100
    assert held.values is frames[0].values  # shared, not copied
    assert frames[-1].values[2] == 900 and frames[-1].index == 10 ** 12
    assert [f.index for f in frames[10 ** 12 - 1:]] == [10 ** 12 - 1, 10 ** 12]
    with pytest.raises(IndexError):
        frames[10 ** 12 + 1]


class SlowFace(LinearFace):
    """A face taking 20 ms a step: playback falls behind and skips frames."""

    def step(self, frame, dt: float) -> Pose:
        time.sleep(0.02)
        return super().step(frame, dt)


def test_xface_stream_uploaded_while_one_plays_fast_plays_from_its_first_frame():
    """A 1000 fps stream playing (frames skipped while the face steps) and a 2-frame stream
    uploaded: the playback task died (IndexError: the old stream's skipped frames looked up
    in the new one), silently; RESUME never finished and the stream never ended."""
    mask = " ".join("1" if k == 2 else "0" for k in range(68))

    def fap(count: int, fps: int, name: str) -> str:
        return f"2.1 {name} {fps} {count}\n" + "".join(f"{mask}\n{i} {i % 200}\n" for i in range(count))

    async def main():
        server = await started(SlowFace, limits=ServerLimits(greeting_delay=0.05))
        sub = server.subscribe(maxsize=100000)
        reader, writer, me = await xface_connect(server.port)
        writer.write(task("UPLOAD_FAP", me, 1, fap(2000, 1000, "long")) + task("RESUME_PLAYBACK", me, 2))
        await expect(reader, 5)
        await asyncio.sleep(0.5)
        writer.write(task("UPLOAD_FAP", me, 3, fap(2, 25, "short")))
        got = await expect(reader, 4)
        assert n("RESUME_PLAYBACK", me, 2, 3) in got  # the playback went on, into the new stream, and finished
        events = []
        while not sub._queue.empty():
            events.append(await sub.get())
        playback = server.stage.playback
        writer.close()
        await server.close()
        return events, playback

    events, playback = run(main())
    assert playback is None or playback.exception() is None
    assert isinstance(events[-1], StreamEnd)
    assert [e.index for e in events if isinstance(e, FrameEvent)][-2:] == [0, 1]  # the new stream, from its start


def test_an_xface_task_declaring_entities_is_refused_before_it_is_parsed():
    """A 7.7 MiB task whose <param> named a declared entity 2.7 million times expanded to
    gigabytes on the server's event loop and stalled every client."""
    from fae.net.xface import TaskFormatError, parse_task

    doc = f'<!DOCTYPE task [<!ENTITY a "{"x" * 250}">]><task name="UPLOAD_FAP" ownerId="0" taskId="1"><param>' \
          + "&a;" * 1000 + "</param></task>"
    with pytest.raises(TaskFormatError, match="DOCTYPE"):
        parse_task(doc.encode())


def test_an_xface_task_of_millions_of_elements_is_refused_before_it_is_parsed():
    """8 MiB of 2 million empty elements, well-formed, took the parser 0.65 s on the
    server's loop (another client's replies waited 1.8-3.4 s) and 55 MB in the task queue."""
    from fae.net.xface import MAX_ELEMENTS, TaskFormatError, parse_task

    doc = b'<task name="UPLOAD_FAP" ownerId="0" taskId="1">' + b"<p/>" * 2_000_000 + b"</task>"
    with pytest.raises(TaskFormatError, match=f"at most {MAX_ELEMENTS} elements"):  # counted, not parsed
        parse_task(doc)
    params = b"".join(b"<param>%d</param>" % i for i in range(100))
    assert len(parse_task(b'<task name="X" ownerId="1" taskId="2">' + params + b"</task>").params) == 100


def test_fae_send_gives_up_on_a_server_that_stops_reading(tmp_path):
    """A server that accepts and never reads: `fae send` waited for ever (and through
    Ctrl-C) on the bytes it could not send; now it stops after --timeout. (Run as a
    process with a deadline: the old client hangs rather than fails.)"""
    import socket
    import subprocess
    import sys

    mask = " ".join("1" if k == 2 else "0" for k in range(68))
    big = tmp_path / "big.fap"
    big.write_text("2.1 big 25 200000\n" + "".join(f"{mask}\n{i} {i % 300}\n" for i in range(200000)))  # 28 MB
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]
        proc = subprocess.Popen([sys.executable, "-m", "fae", "send", str(big), "--port", str(port), "--timeout", "1"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        conn, _ = listener.accept()  # accepted, never read
        try:
            _, err = proc.communicate(timeout=60)
        finally:
            proc.kill()
            conn.close()
    assert proc.returncode == 2 and f"127.0.0.1:{port}: " in err and " for 1 s" in err, err


@pytest.mark.parametrize("command", ["send", "serve"])
def test_a_port_out_of_range_is_one_line(command, capsys):
    """--port 70000 gave an OverflowError traceback (fae serve after loading its head)."""
    from fae.cli import main

    args = [command, "fap_streams/visemes.fap"] if command == "send" else [command]
    assert main([*args, "--port", "70000"]) == 2
    assert capsys.readouterr().err.strip() == f"fae {command}: --port 70000: expected 0..65535"


def test_a_client_that_takes_none_of_its_replies_is_closed_after_a_while():
    """Case: clients that sent frames and never read waited on for ever (the server's
    replies blocked on a full socket; counted busy, never idle): 16 of them locked every
    other client of their address out. One that takes nothing for STALLED_SECONDS is closed."""
    from fae.net.connection import Connection

    class Stuck:  # a socket whose buffers are full: drain never returns
        def __init__(self):
            self.aborted = False
            self.transport = self

        def get_extra_info(self, name):
            return ("127.0.0.1", 5)

        def get_write_buffer_size(self):
            return 0

        def is_closing(self):
            return self.aborted

        def abort(self):
            self.aborted = True

        def write(self, data):
            pass

        async def drain(self):
            await asyncio.Event().wait()

    async def main():
        writer = Stuck()
        conn = Connection(7, None, writer)
        started = time.monotonic()
        sent = await conn.send_and_drain(b"ok 1 1\n", stalled=0.2)
        return sent, time.monotonic() - started, writer.aborted, conn.closing

    sent, waited, aborted, closing = run(main())
    assert not sent and aborted and closing and 0.15 < waited < 5
