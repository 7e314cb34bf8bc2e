"""Author the sample FAP streams in fap_streams/ (deterministic: same files on every run).

    .venv/bin/python tools/make_fap_streams.py [OUT_DIR]      (default: fap_streams/)

All files are .fap v2.1 at 25 fps, every frame sends the FAPs the file drives, values are
integers in FAPU (or AU = 1e-5 rad), and fae reads them without warnings.

expressions.fap    the six basic expressions (joy, sadness, anger, fear, disgust,
                   surprise) from LOW-LEVEL FAPs only, in that order: each rises for 0.5 s
                   (smoothstep), holds for 1.0 s, releases for 0.5 s, then 0.2 s of
                   neutral: 13.2 s. The faces are the FAP 2 table's poses
                   (fae.animate.highlevel.EXPRESSION_POSES: what a stream sending FAP 2 at
                   full intensity shows), each with a head motion (HEAD_MOTION: sadness
                   and anger nod down, fear and surprise lift the head, disgust turns it
                   away). The poses give the lips relative to the jaw; the file sends them
                   as the standard's displacements from neutral, which open_jaw does not
                   change (fae.animate.highlevel.jaw_carried).
visemes.fap        "Thank you, Bob." as a FAP 1 viseme sequence (TH aa nn kk ih ou sil PP oh
                   PP sil), 4 frames per viseme, each blending in from the previous one over
                   2 frames (viseme_select2 = previous, viseme_blend 32 then 63).
eyes_head.fap      10 s: gaze left, right, up, down (eyeball yaw/pitch 0.2 rad, both eyes),
                   three blinks (upper lids down one iris diameter, 1024 IRISD units, in
                   3 frames and back in 4), two nods (head pitch +-0.1 rad), a head turn each
                   way (yaw +-0.25 rad) and a tilt (roll 0.1 rad).
all_faps_sweep.fap every low-level FAP 3..68 in turn, alone: 0 -> max -> 0 -> min -> 0
                   (unidirectional FAPs 0 -> max -> 0), 6 frames per leg, 2 frames at 0
                   between FAPs, through the standard's full range (I range x quantiser
                   step). That range is the coder's and exceeds anatomy for the angle FAPs
                   (head pitch +-3.16 rad): the file is a stress test of every FAP, not a
                   performance.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from fae.animate.highlevel import EXPRESSION_POSES, jaw_carried  # noqa: E402
from fae.io.fap import FapFrame, FapHeader, Viseme, write_fap  # noqa: E402
from fae.mpeg4.faps import FAP_COUNT, FAPS  # noqa: E402
from fae.mpeg4.highlevel import viseme_by_name  # noqa: E402

FPS = 25


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def envelope(n_frames: int, rise: float, hold: float, release: float) -> np.ndarray:
    """(n_frames,) weights 0..1: smoothstep rise, hold at 1, smoothstep release, then 0."""
    t = np.arange(n_frames) / FPS
    up = smoothstep(t / rise)
    down = 1.0 - smoothstep((t - rise - hold) / release)
    return np.minimum(up, down)


def frames_from_tracks(tracks: dict[int, np.ndarray], n_frames: int) -> list[FapFrame]:
    """FAP number -> (n_frames,) values; every frame sends all tracked FAPs."""
    mask = np.zeros(FAP_COUNT, dtype=bool)
    for number in tracks:
        mask[number - 1] = True
    frames = []
    for k in range(n_frames):
        values = np.zeros(FAP_COUNT)
        for number, track in tracks.items():
            values[number - 1] = float(np.rint(track[k]))
        frames.append(FapFrame(k, mask.copy(), values))
    return frames


# each expression's head motion (FAPs 48-50, AU), added to its face (EXPRESSION_POSES)
HEAD_MOTION: dict[str, dict[int, float]] = {
    "sadness": {48: 6000}, "anger": {48: 2000}, "fear": {48: -4000}, "disgust": {49: 3000}, "surprise": {48: -3000},
}


def expressions_frames() -> list[FapFrame]:
    rise, hold, release, rest = 0.5, 1.0, 0.5, 0.2
    per = int(round((rise + hold + release + rest) * FPS))
    weights = envelope(per, rise, hold, release)
    poses = [jaw_carried({**pose, **HEAD_MOTION.get(name, {})}) for name, pose in EXPRESSION_POSES.items()]
    used = sorted({number for pose in poses for number in pose})
    n_frames = per * len(poses)
    tracks = {number: np.zeros(n_frames) for number in used}
    for i, pose in enumerate(poses):
        for number, value in pose.items():
            tracks[number][i * per:(i + 1) * per] = value * weights
    return frames_from_tracks(tracks, n_frames)


PHRASE = ("TH", "aa", "nn", "kk", "ih", "ou", "sil", "PP", "oh", "PP", "sil")


def visemes_frames() -> list[FapFrame]:
    mask = np.zeros(FAP_COUNT, dtype=bool)
    mask[0] = True
    frames = []
    previous = 0
    k = 0
    for name in ("sil",) + PHRASE:
        code = viseme_by_name(name).code
        for step in range(4):
            blend = 32 if step == 0 else 63
            values = np.zeros(FAP_COUNT)
            values[0] = code
            frames.append(FapFrame(k, mask.copy(), values, Viseme(code, previous, blend, 0)))
            k += 1
        previous = code
    return frames


def eyes_head_frames() -> list[FapFrame]:
    n_frames = 10 * FPS
    t = np.arange(n_frames) / FPS
    tracks = {number: np.zeros(n_frames) for number in (19, 20, 23, 24, 25, 26, 48, 49, 50)}

    def bump(start: float, duration: float) -> np.ndarray:  # smooth 0 -> 1 -> 0
        x = np.clip((t - start) / duration, 0.0, 1.0)
        return np.sin(np.pi * x) ** 2

    gaze_yaw = 20000 * (bump(0.2, 1.2) - bump(1.5, 1.2))  # 0.2 rad left, then right
    gaze_pitch = 20000 * (-bump(2.8, 1.0) + bump(3.9, 1.0))  # up, then down (positive = down)
    for number in (23, 24):
        tracks[number] += gaze_yaw
    for number in (25, 26):
        tracks[number] += gaze_pitch
    for start in (1.4, 5.0, 8.6):  # blinks: 3 frames closing, 4 opening
        k0 = int(round(start * FPS))
        lid = np.interp(np.arange(8), [0, 3, 7], [0, 1024, 0])
        for number in (19, 20):
            tracks[number][k0:k0 + 8] = lid
    tracks[48] += 10000 * (bump(5.0, 0.6) + bump(5.6, 0.6))  # two nods (down, 0.1 rad)
    tracks[49] += 25000 * (bump(6.4, 1.0) - bump(7.4, 1.0))  # turn left, then right
    tracks[50] += 10000 * bump(8.5, 1.3)  # tilt toward the right shoulder
    return frames_from_tracks(tracks, n_frames)


def sweep_frames() -> list[FapFrame]:
    leg, rest = 6, 2
    frames = []
    k = 0
    for info in FAPS[2:]:
        low, high = info.value_range
        if info.bidirectional and low < 0:
            keys = [0.0, high, 0.0, low, 0.0]
        else:
            keys = [0.0, high, 0.0]
        track = np.concatenate([np.linspace(a, b, leg, endpoint=False) for a, b in zip(keys[:-1], keys[1:])]
                               + [np.zeros(rest)])
        mask = np.zeros(FAP_COUNT, dtype=bool)
        mask[info.number - 1] = True
        for value in track:
            values = np.zeros(FAP_COUNT)
            values[info.number - 1] = float(np.rint(value))
            frames.append(FapFrame(k, mask.copy(), values))
            k += 1
    return frames


STREAMS = {
    "expressions.fap": ("fae expressions joy sadness anger fear disgust surprise", expressions_frames),
    "visemes.fap": ("fae visemes Thank you Bob", visemes_frames),
    "eyes_head.fap": ("fae eyes and head", eyes_head_frames),
    "all_faps_sweep.fap": ("fae sweep of FAPs 3-68", sweep_frames),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out_dir = Path(argv[0]) if argv else REPO / "fap_streams"
    out_dir.mkdir(parents=True, exist_ok=True)
    for file_name, (name, build) in STREAMS.items():
        frames = build()
        count = write_fap(out_dir / file_name, FapHeader("2.1", name, float(FPS), len(frames)), frames)
        print(f"{out_dir / file_name}: {count} frames, {count / FPS:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
