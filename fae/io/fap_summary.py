"""What a .fap stream holds, in one pass: the summary `fae inspect` prints.

    summarize_fap(path) -> dict
"""

from __future__ import annotations

import os

import numpy as np

from fae.io.fap import read_fap
from fae.io.frames import WARN_HIGH, WARN_LOW
from fae.mpeg4.faps import FAP_COUNT, FAPS
from fae.mpeg4.faptables import FAP_LIMITS


def summarize_fap(path: str | os.PathLike) -> dict:
    """Read the .fap file `path` fully (streaming) and summarize it; raises FapFormatError.

    Returns {path, version, name, fps, frame_count, declared_frame_count,
    first_frame_number, last_frame_number, duration_s, faps_used (FAP numbers),
    value_ranges (FAP number as str -> [low, high] in the FAP's units), visemes_used,
    expressions_used, warnings (what was accepted with a warning, one line each; a
    low-level FAP sent beyond the range the player clamps to, FAP_LIMITS, is one, as the
    player warns of it: a unidirectional FAP sent slightly negative is not)}."""
    stream = read_fap(path)
    ever = np.zeros(FAP_COUNT, dtype=bool)
    low = np.full(FAP_COUNT, np.inf)
    high = np.full(FAP_COUNT, -np.inf)
    first_number = last_number = None
    visemes: set[int] = set()
    expressions: set[int] = set()
    for frame in stream:
        if first_number is None:
            first_number = frame.number
        last_number = frame.number
        ever |= frame.mask
        sent = frame.mask
        low[sent] = np.minimum(low[sent], frame.values[sent])
        high[sent] = np.maximum(high[sent], frame.values[sent])
        if frame.viseme is not None:
            visemes.update((frame.viseme.select1, frame.viseme.select2))
        if frame.expression is not None:
            expressions.update((frame.expression.select1, frame.expression.select2))
    header = stream.header
    used = [int(i) + 1 for i in np.flatnonzero(ever)]
    beyond = [f"FAP {n} {FAPS[n - 1].name}: values {low[n - 1]:g} .. {high[n - 1]:g} go beyond the range played, "
              f"{FAP_LIMITS[n - 1, 0]:g} .. {FAP_LIMITS[n - 1, 1]:g} {FAPS[n - 1].fapu or ''}".rstrip()
              + ": clamped to it"
              for n in used if low[n - 1] < WARN_LOW[n - 1] or high[n - 1] > WARN_HIGH[n - 1]]
    frame_count = stream.frame_count or 0
    span = (last_number - first_number + 1) if first_number is not None else 0
    return {
        "path": str(path),
        "version": header.version,
        "name": header.name,
        "fps": header.fps,
        "frame_count": frame_count,
        "declared_frame_count": header.declared_frame_count,
        "first_frame_number": first_number,
        "last_frame_number": last_number,
        "duration_s": span / header.fps,
        "faps_used": used,
        "value_ranges": {str(n): [float(low[n - 1]), float(high[n - 1])] for n in used},
        "visemes_used": sorted(visemes),
        "expressions_used": sorted(expressions),
        "warnings": list(stream.warnings) + beyond,
    }
