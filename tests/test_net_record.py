"""Recording what the server plays: the mp4 holds every frame sent, in order, each pose held
until the next one (the stream's clock for native streams, the wall clock for Xface)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from fae.net.client import send_fap
from fae.net.faces import Pose
from fae.net.hub import FrameEvent
from fae.net.record import RecordingClock, StreamRecorder
from fae.net.server import FapServer
from test_net_server import LinearFace, fap_text

pytest.importorskip("fae.render.video")


class GreyRenderer:
    """Paints the whole image one grey level: the render's count, so decoding tells order."""

    def __init__(self) -> None:
        self.count = 0

    def render(self, skin_vertices, bone_transforms, pupil_scale):
        assert skin_vertices.shape == LinearFace.rest.shape
        image = np.full((64, 64, 3), (self.count * 5) % 250, dtype=np.uint8)
        self.count += 1
        return image

    def close(self) -> None:
        pass


def decoded_grey_levels(path) -> list[float]:
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    w, h = meta["size"]
    return [float(np.frombuffer(f, np.uint8).reshape(h, w, 3).mean()) for f in reader]


def test_record_writes_every_frame_of_a_stream_and_appears_only_when_closed(tmp_path):
    out = tmp_path / "live.mp4"
    text = fap_text()  # 43 frames

    async def main():
        server = FapServer(LinearFace, port=0)
        await server.start()
        recorder = StreamRecorder(server.subscribe(maxsize=4, lossless=True), out, GreyRenderer, (64, 64))
        recorder.start()
        report = await send_fap(text, port=server.port)
        assert report.complete
        assert not out.exists()  # still recording
        await server.close()
        await recorder.close()
        return recorder, report

    recorder, report = run_main(main())
    assert out.is_file() and recorder.frames_written == 43 and recorder.skipped == 0
    # One render per face step; frames coalesced into one step repeat its image.
    assert recorder.frames_rendered == report.steps
    levels = decoded_grey_levels(out)
    assert len(levels) == 43
    expected = [(k * 5) % 250 for k in np.repeat(np.arange(report.steps), np.bincount(report.frame_steps - 1))]
    np.testing.assert_allclose(levels, expected, atol=3)
    assert not [p for p in tmp_path.iterdir() if p.name != "live.mp4"]  # no temporary left behind


def test_record_follows_one_stream_at_a_time(tmp_path):
    out = tmp_path / "two.mp4"
    text = fap_text()

    async def main():
        server = FapServer(LinearFace, port=0)
        await server.start()
        recorder = StreamRecorder(server.subscribe(maxsize=4, lossless=True), out, GreyRenderer, (64, 64))
        recorder.start()
        reports = await asyncio.gather(send_fap(text, port=server.port), send_fap(text, port=server.port))
        assert all(r.complete for r in reports)
        await server.close()
        await recorder.close()
        return recorder

    recorder = run_main(main())
    # Whichever stream came first is recorded whole; the other's overlapping frames are skipped.
    assert recorder.frames_written + recorder.skipped == 86
    assert recorder.frames_written >= 43
    assert len(decoded_grey_levels(out)) == recorder.frames_written


def run_main(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


def numbered_stream(numbers: list[int], fps: int = 25) -> str:
    """A .fap text whose frames carry `numbers` (gaps: frames not sent), each moving FAP 3."""
    mask = " ".join("1" if k == 2 else "0" for k in range(68))
    body = "".join(f"{mask}\n{number} {100 * (i + 1)}\n" for i, number in enumerate(numbers))
    return f"2.1 gaps {fps} {len(numbers)}\n{body}"


def recorded(numbers: list[int], out, fps: float | None = None) -> StreamRecorder:
    """The recorder of a server to which one native client sent frames numbered `numbers`
    (a 25 fps stream), each after the previous one's ack (one pose each); video at `fps`
    (None: the stream's)."""

    async def main():
        server = FapServer(LinearFace, port=0)
        await server.start()
        recorder = StreamRecorder(server.subscribe(maxsize=4, lossless=True), out, GreyRenderer, (64, 64), fps=fps)
        recorder.start()
        header, *lines = numbered_stream(numbers).splitlines()
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(f"{header}\n".encode())
        assert (await reader.readline()).startswith(b"ok header")
        for mask, values in zip(lines[::2], lines[1::2]):
            writer.write(f"{mask}\n{values}\n".encode())
            assert (await reader.readline()).startswith(f"ok {values.split()[0]} ".encode())
        writer.close()
        await server.close()
        await recorder.close()
        return recorder

    return run_main(main())


def test_a_native_stream_that_skips_frame_numbers_keeps_its_own_clock(tmp_path):
    """One frame a second on a 25 fps stream (numbers 0, 25, 50, 75): each pose is held
    for a second of video, however fast the frames were sent."""
    out = tmp_path / "gaps.mp4"
    recorder = recorded([0, 25, 50, 75], out)
    assert recorder.frames_written == 76 and recorder.frames_rendered == 4
    levels = decoded_grey_levels(out)
    np.testing.assert_allclose(levels, [0] * 25 + [5] * 25 + [10] * 25 + [15], atol=3)


def event(stream: str, index: int, made: float, fps: float = 25.0) -> FrameEvent:
    return FrameEvent(stream, index, index / fps, fps, Pose(LinearFace.rest, {}), made=made)


def test_xface_frames_fall_on_the_wall_clock_and_a_following_stream_starts_one_frame_later():
    clock = RecordingClock(1 / 25)
    # Xface uploads of one frame each (every one numbered 0), played 1.0 s and 2.5 s apart.
    times = [clock.place(event("xface", 0, made), starts_stream=True) for made in (100.0, 101.0, 103.5)]
    assert times == pytest.approx([0.0, 1.0, 3.5])
    # A playback: its frames were played 40 ms apart.
    times = [clock.place(event("xface", k, 104.0 + k / 25), starts_stream=k == 0) for k in range(3)]
    assert times == pytest.approx([4.0, 4.04, 4.08])
    # A native stream then keeps its own clock from one frame after the last pose.
    times = [clock.place(event("native-3", k, made=500.0), starts_stream=k == 0) for k in (0, 1, 26)]
    assert times == pytest.approx([4.12, 4.16, 5.16])
    # Back to Xface after a native stream: it starts one frame later, not at its wall time.
    assert clock.place(event("xface", 0, 900.0), starts_stream=True) == pytest.approx(5.2)


def test_a_gap_of_a_trillion_frames_is_held_for_max_hold_seconds(tmp_path):
    """Frame 0 then frame 10^12 (legal: numbers may skip): the recorder wrote the first pose
    10^12 times (the server never stopped, the file never appeared). The hold is cut to
    MAX_HOLD_SECONDS and the frames after it keep their spacing."""
    from fae.io.frames import MAX_HOLD_SECONDS

    out = tmp_path / "gap.mp4"
    recorder = recorded([0, 10**12, 10**12 + 25], out, fps=1.0)
    assert recorder.gaps_cut == 1
    # at 1 frame/s: the first pose for MAX_HOLD_SECONDS, the second for the second between them, the last once
    assert recorder.frames_written == MAX_HOLD_SECONDS + 1 + 1 and out.is_file()
