"""FaceDefTables baked from a head's own physics (the standard's Predictable profile).

For every low-level FAP that moves the skin (`SKIN_TRANSLATION_FAPS`: 3-22, 31-42, 51-68)
the physics Player holds the FAP alone at each border of its table, from the neutral face,
until the skin settles (no vertex moves more than `settled` metres in a frame, as
verify-faps holds a value). The borders split each sign of the range the Player clamps to
(`FAP_LIMITS`) into `intervals_per_side` equal intervals. With d(b) the settled skin
displacement at border b (d(0) = 0), interval j gets the rate

    D_j = (d(b_j+1) - d(b_j)) / (b_j+1 - b_j)        metres per FAP unit,

so the standard's piecewise-linear sum (fae.animate.facedef) gives back d exactly at every
border and interpolates between them. Only vertices that move more than `threshold` metres
at some border are listed. The jaw, eyeballs, head and tongue stay rigid poses (bone
transforms, fae.animate.rigid): the tables of the jaw FAPs (3, 14, 15) hold the skin that
the mandible carries, not the mandible. Ear FAPs (65-68) bake the ear tables the Player
derives (fae.animate.ears), so a baked head plays its ears the same way.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np

from fae.mpeg4.faptables import FAP_LIMITS, SKIN_TRANSLATION_FAPS
from fae.animate.verify import settled_skin  # the settled pose, as verify-faps holds a FAP
from fae.io.facemodel import FaceDefTable
from fae.mpeg4.faps import FAP_COUNT

INTERVALS_PER_SIDE = 3
THRESHOLD = 1e-5  # metres (0.01 mm): a vertex moving less at every border is left out


def table_borders(fap: int, intervals_per_side: int = INTERVALS_PER_SIDE) -> np.ndarray:
    """(m + 1,) FAP values (FAPU units), increasing, containing 0: the borders of `fap`'s table."""
    lo, hi = FAP_LIMITS[fap - 1]
    steps = np.arange(1, intervals_per_side + 1) / intervals_per_side
    return np.concatenate([lo * steps[::-1] if lo < 0 else [], [0.0], hi * steps if hi > 0 else []])


def bake_table(player, fap: int, intervals_per_side: int = INTERVALS_PER_SIDE, threshold: float = THRESHOLD,
               **settle) -> FaceDefTable | None:
    """The skin FaceDefTable of `fap` from `player`'s physics (None when it moves no vertex
    more than `threshold` metres)."""
    borders = table_borders(fap, intervals_per_side)
    rest = np.asarray(player.face.skin_vertices, dtype=np.float64)
    moved = np.zeros((len(borders), len(rest), 3))  # d(b), metres
    for i, b in enumerate(borders):
        if b != 0.0:
            values = np.zeros(FAP_COUNT)
            values[fap - 1] = b
            moved[i] = settled_skin(player, values, **settle) - rest
    keep = np.flatnonzero(np.linalg.norm(moved, axis=2).max(axis=0) > threshold)
    if len(keep) == 0:
        return None
    rates = np.diff(moved[:, keep], axis=0) / np.diff(borders)[:, None, None]
    return FaceDefTable(fap, "skin", keep.astype(np.int32), borders.astype(np.float64), rates, source="physics")


def bake_tables(player, faps=None, intervals_per_side: int = INTERVALS_PER_SIDE, threshold: float = THRESHOLD,
                progress: Callable[[int, int], None] | None = None, **settle) -> list[FaceDefTable]:
    """Skin FaceDefTables (source "physics") of `faps` (default every skin-moving FAP) from the
    physics Player `player`; `progress(done, total)` after each FAP."""
    faps = list(SKIN_TRANSLATION_FAPS if faps is None else faps)
    for k in faps:
        if k not in SKIN_TRANSLATION_FAPS:
            raise ValueError(f"FAP {k}: not a FAP that moves the skin (expected one of 3-22, 31-42, 51-68)")
    tables = []
    for done, k in enumerate(faps, 1):
        table = bake_table(player, k, intervals_per_side, threshold, **settle)
        if table is not None:
            tables.append(table)
        if progress is not None:
            progress(done, len(faps))
    return tables


def baked_model(face, tables: list[FaceDefTable], faps=None):
    """A copy of FaceModel `face` whose FaceDefTable slot holds its authored tables and `tables`
    (earlier baked tables are replaced). `faps`: the FAPs that were baked (default: those of
    `tables`), recorded in the head's meta "face_def_tables_baked": a FAP baked without a
    table (no vertex moved past THRESHOLD) is then told from one never baked."""
    baked = {int(t.fap) for t in tables} | ({int(k) for k in faps} if faps is not None else set())
    out = copy.copy(face)
    out.face_def_tables = [t for t in face.face_def_tables if t.source == "authored"] + list(tables)
    out.meta = {**(face.meta or {}), "face_def_tables_baked": sorted(baked)}
    return out


def baked_faps(face) -> set[int]:
    """FAP numbers `face`'s physics tables were baked for: those its meta records (a FAP that
    moved nothing has no table) and those with a table."""
    recorded = (face.meta or {}).get("face_def_tables_baked", ())
    recorded = recorded if isinstance(recorded, (list, tuple)) else ()
    return ({int(k) for k in recorded if isinstance(k, (int, float)) and not isinstance(k, bool) and k == int(k)}
            | {int(t.fap) for t in face.face_def_tables if t.source == "physics"})


def has_baked_tables(face) -> bool:
    """True when `face` carries FaceDefTables baked from its physics."""
    return any(t.source == "physics" for t in face.face_def_tables)
