"""Recording what the server plays: the mp4 holds every frame sent, in order."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from fae.net.client import send_fap
from fae.net.record import StreamRecorder
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
