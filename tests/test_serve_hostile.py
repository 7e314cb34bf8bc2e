"""`fae serve` against hostile clients: a real server process on 127.0.0.1 with the real
Player, small limits so that the tests reach them quickly, and a well-behaved client that
must still be served. Every wait is bounded; the bounds prove "does not hang", not speed.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from fae.net.client import send_fap
from test_net_server import expect, n, task, xface_connect
from test_serve_e2e import ServeProcess, head  # noqa: F401  (the fixture)

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
STREAM = REPO / "fap_streams" / "visemes.fap"  # 48 frames at 25 fps, shipped
IDLE_TIMEOUT = 3.0
PER_ADDRESS = 8


def run(coro, timeout: float = 120.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture(scope="module")
def server(head):  # noqa: F811
    proc = ServeProcess("--head", str(head), "--idle-timeout", str(IDLE_TIMEOUT), "--max-clients", "16",
                        "--max-per-address", str(PER_ADDRESS))
    yield proc
    if proc.proc.poll() is None:
        proc.proc.kill()


def rss_mb(proc) -> float:
    for line in Path(f"/proc/{proc.pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def frame_lines(number: int, open_jaw: int) -> str:
    mask = ["0"] * 68
    mask[2] = "1"
    return " ".join(mask) + f"\n{number} {open_jaw}\n"


async def well_behaved(port: int) -> None:
    report = await send_fap(STREAM.read_text(), port=port, rate="max", timeout=60)
    assert report.complete, report.summary()


async def silent_sockets(port: int, count: int, source: str = "127.0.0.1") -> list:
    return [await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0)) for _ in range(count)]


async def closed_within(reader: asyncio.StreamReader, seconds: float) -> bool:
    """True when the server closes this socket within `seconds` (greeting bytes skipped)."""
    deadline = time.monotonic() + seconds
    try:
        while (left := deadline - time.monotonic()) > 0:
            if not await asyncio.wait_for(reader.read(65536), left):
                return True
    except (asyncio.TimeoutError, ConnectionError):
        return False
    return False


def test_idle_sockets_cannot_lock_a_client_out_and_are_closed_when_idle(server):
    """Case: 200 silent sockets used to hold every place for good. Now one address holds at
    most its share, a newcomer takes the place of the socket idle longest, and silent
    sockets are closed after the idle timeout."""

    async def main():
        horde = await silent_sockets(server.port, 40)
        await asyncio.sleep(1.5)  # idle long enough to make room for a newcomer
        await well_behaved(server.port)  # same address as the horde
        closed = await asyncio.gather(*(closed_within(r, IDLE_TIMEOUT + 10) for r, _ in horde))
        for _, w in horde:
            w.close()
        return closed

    assert all(run(main()))
    assert server.wait_for_line(r"idle for 3 s; closing"), "".join(server.lines)


def test_one_address_holds_at_most_its_share_of_places(server):
    async def main():
        horde = await silent_sockets(server.port, 30, source="127.0.0.2")
        refused = await asyncio.gather(*(closed_within(r, 0.5) for r, _ in horde))
        await well_behaved(server.port)  # another address: served without waiting for anyone
        for _, w in horde:
            w.close()
        return refused

    refused = run(main())
    assert sum(not r for r in refused) == PER_ADDRESS


def test_frame_gaps_and_a_tiny_fps_cost_what_one_frame_costs(server):
    """Case: frames 0 and 12500 at 25 fps (dt = 500 s) stalled every client for seconds; a
    header fps of 0.01 cost 4 s of CPU a frame. Each is now one bounded step: a trillion-
    frame gap is answered like any frame, and a client streaming beside them is served."""

    async def stream(header: str, numbers: list[int]) -> list[str]:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write((header + "\n" + "".join(frame_lines(k, 300 * (i % 2)) for i, k in enumerate(numbers))).encode())
        writer.write_eof()
        replies = []
        while line := await asyncio.wait_for(reader.readline(), 60):
            replies.append(line.decode().strip())
        writer.close()
        return replies

    async def main():
        gaps = [0, 12_500, 25_000, 10 ** 12, 10 ** 15]
        started = time.monotonic()
        attackers = [stream("2.1 gaps 25 5", gaps), stream("2.1 slow 0.01 5", list(range(5)))] * 2
        replies = await asyncio.gather(*attackers, well_behaved(server.port))
        return replies, time.monotonic() - started, gaps

    replies, seconds, gaps = run(main())
    assert [r.split()[1] for r in replies[0] if r.startswith("ok ") and "header" not in r] == [str(k) for k in gaps]
    assert replies[0][-1].startswith("done 5 frames") and replies[1][-1].startswith("done 5 frames")
    assert seconds < 60


def test_an_upload_with_a_huge_frame_number_keeps_memory_flat(server):
    """Case: an UPLOAD_FAP of frames 0 and 300000 took 300 MB and kept it. Frames 0 and 10**9
    (40 days at 25 fps) now cost two frames; it plays, and stops, like any stream."""
    text = "2.1 gap 25 2\n" + frame_lines(0, 300) + frame_lines(10 ** 9, 600)

    async def main():
        before = rss_mb(server.proc)
        reader, writer, owner = await xface_connect(server.port)
        writer.write(task("UPLOAD_FAP", owner, 1, text) + task("RESUME_PLAYBACK", owner, 2))
        got = await expect(reader, 5, timeout=60)
        writer.write(task("STOP_PLAYBACK", owner, 3))
        got += await expect(reader, 2, timeout=60)
        writer.close()
        return before, rss_mb(server.proc), owner, got

    before, after, owner, got = run(main())
    assert sorted(got) == sorted([n("UPLOAD_FAP", owner, 1, 1), n("RESUME_PLAYBACK", owner, 2, 1),
                                  n("UPLOAD_FAP", owner, 1, 2), n("UPLOAD_FAP", owner, 1, 3),
                                  n("RESUME_PLAYBACK", owner, 2, 2),
                                  n("STOP_PLAYBACK", owner, 3, 1), n("STOP_PLAYBACK", owner, 3, 3)])
    assert after - before < 50, f"server memory {before:.0f} -> {after:.0f} MB"


def test_client_chosen_strings_reach_the_log_bounded(server):
    """Case: a 5,000-digit ownerId was written into the log in full."""
    owner_digits = "5" * 5000

    async def main():
        reader, writer, owner = await xface_connect(server.port)
        mark = len(server.lines)
        writer.write(f'<task name="STOP_PLAYBACK" ownerId="{owner_digits}" taskId="1"></task>'.encode() + b"\0")
        writer.write(task("X" * 5000, owner, 2) + task("LOAD_FAP", owner, 3, "a/" * 3000 + "x.fap"))
        got = await expect(reader, 4, timeout=30)
        writer.close()
        await asyncio.sleep(0.5)  # the log lines reach the test's reader thread
        return mark, got

    mark, got = run(main())
    assert got[0] == got[1] == '<notify name="ERROR" ownerId="0" taskId="0" status="7"/>'
    log = server.lines[mark:]
    assert log and max(len(line) for line in log) < 1200
    assert "5" * 100 not in "".join(log) and "X" * 100 not in "".join(log)
    assert "5000 characters" in "".join(log)
