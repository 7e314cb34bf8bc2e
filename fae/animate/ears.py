"""The ears (FAPs 65-68) as FaceDefTables derived from the head, not simulated.

An ear is cartilage: FAP 65 raises the left ear, 67 pulls it sideways (66, 68 the right),
and it moves as a whole. Each ear FAP whose feature point (10.1-10.4) lies on the skin gets
a table that carries the ear rigidly by value x FAPU along the FAP's direction and fades
into the scalp around it, so the feature point moves exactly as the standard says and the
skin solver spends nothing on the ears (fae.sim simulates only skin near muscles).

The ear is the skin region of the feature point's triangle when that region's name says
"ear" (the generic head and every head adapted from it); around it the weight falls with
geodesic distance from the ear's rim (`ear_rim`; the heat method's, potpourri3d:
Dijkstra's along edges zig-zags, and a triangle whose corners' distances came by different
zig-zags got a gradient twice the fade's, which turned 27 triangles under the jaw over at
the limit) as the smoothstep
1 - 3 r^2 + 2 r^3 over a fade that widens with the value: `FADE_ES` x ES0 while the ear
has moved at most GRADIENT x that / SMOOTHSTEP_SLOPE, then as far as keeps the skin's
displacement gradient within GRADIENT (an edge along the motion at most 1 + GRADIENT, one
against it at least 1 - GRADIENT its rest length). The
standard lets an ear move 900 ENS units (5 cm on the generic head): over a fixed 1.3 cm
fade the scalp at the ear's root stretched 7.5x. The table holds the fields at doubling
values up to the limit and the standard's piecewise-linear rule blends between them, so a
twitch moves the skin near the ear only and the limit moves the side of the head. On a
head without an ear region the motion fades from the feature point's triangle, over at
least `DISC_ES` x ES0.
A head's own (authored) FaceDefTable for an ear FAP takes precedence (the standard's
Predictable case); a table baked from the physics (fae.animate.bake) is this one's copy.
"""

from __future__ import annotations

import numpy as np
import potpourri3d
from scipy.sparse.csgraph import connected_components

from fae.mpeg4.faptables import FAP_DIRECTION, FAP_FEATURE_POINT, FAP_LIMITS, fap_unit_scale
from fae.io.facemodel import FaceDefTable
from fae.mesh import adjacency

EAR_FAPS = (65, 66, 67, 68)
FADE_ES = 0.2  # the narrowest fade, x ES0
DISC_ES = 0.5  # the narrowest fade on a head without an ear region, x ES0
GRADIENT = 0.6  # the largest displacement gradient the fade allows (metres per metre)
SMOOTHSTEP_SLOPE = 1.5  # the largest slope of 1 - 3 r^2 + 2 r^3 over r in [0, 1]


def ear_tables(face, fapu: dict[str, float]) -> list[FaceDefTable]:
    """FaceDefTables (part "skin") of the ear FAPs of `face`."""
    own = {t.fap for t in face.face_def_tables if t.source == "authored"}  # a baked table is the physics' copy of these
    unit = fap_unit_scale(face)
    es0 = fapu["ES"] * 1024.0
    faces = np.asarray(face.skin_faces)
    names = list(face.region_names)
    region = np.asarray(face.skin_region)
    out = []
    geodesic = None
    for k in EAR_FAPS:
        point = face.feature_points.get(FAP_FEATURE_POINT[k - 1])
        if k in own or point is None or point.part != "skin":
            continue
        tri = faces[point.triangle]
        regions = {int(r) for r in region[tri]} if len(region) else set()
        if len(regions) == 1 and "ear" in names[regions.pop()]:
            ear, narrowest = np.flatnonzero(region == region[tri[0]]), FADE_ES * es0
        else:
            ear, narrowest = tri, DISC_ES * es0
        limit = float(np.abs(FAP_LIMITS[k - 1]).max())
        values = fade_values(limit, unit[k - 1], narrowest)
        fades = np.array([fade_width(v * unit[k - 1], narrowest) for v in values])
        if geodesic is None:  # factorized once, for the first ear that needs it, on the vertices in use
            used = np.unique(faces)
            compact = np.full(face.skin_vertex_count, -1)
            compact[used] = np.arange(len(used))
            geodesic = potpourri3d.MeshHeatMethodDistanceSolver(
                np.asarray(face.skin_vertices, dtype=np.float64)[used], compact[faces])
            A = adjacency(faces, face.skin_vertex_count)
            _, component = connected_components(A, directed=False)
        d = np.full(face.skin_vertex_count, np.inf)
        d[used] = geodesic.compute_distance_multisource([int(i) for i in compact[ear_rim(ear, A)] if i >= 0])
        d[ear] = 0.0
        d[~np.isin(component, component[ear])] = np.inf  # the heat method gives other pieces a constant
        idx = np.flatnonzero(d < fades[-1])
        # the skin's displacement at each value (+ and - alike), metres: the ear carried whole
        step = unit[k - 1] * FAP_DIRECTION[k - 1]
        at = [smoothstep_fade(d[idx] / f)[:, None] * (v * step)[None, :] for v, f in zip(values, fades)]
        borders = np.concatenate([-values[::-1], [0.0], values])
        shape = np.concatenate([[-a for a in at[::-1]], [np.zeros((len(idx), 3))], at])  # the integral at each border
        per_unit = np.diff(shape, axis=0) / np.diff(borders)[:, None, None]
        out.append(FaceDefTable(k, "skin", idx.astype(np.int32), borders, per_unit))
    return out


def ear_rim(ear: np.ndarray, A) -> np.ndarray:
    """(r,) the vertices of `ear` (int indices) with a neighbour outside it (A: the skin's
    adjacency), where the fade starts. The heat method's distance from the whole ear as
    sources is flat nowhere inside it: 0 to 13.5 mm over the generic head's ear, so the
    scalp one edge (1.8 mm) from the root lay 13.7 mm off, beyond the narrowest fade, and
    stayed while the ear moved (an ear lowered 5 mm folded 8 triangles at its root). From
    the rim it lies 2-4 mm off."""
    inside = np.zeros(A.shape[0], dtype=bool)
    inside[ear] = True
    outside_neighbours = np.asarray(A[ear] @ (~inside).astype(np.float64)).ravel()
    rim = ear[outside_neighbours > 0]
    return rim if len(rim) else ear


def fade_width(moved: float, narrowest: float) -> float:
    """Metres: the fade around an ear moved `moved` metres, at least `narrowest`, wide
    enough that the displacement's gradient stays within GRADIENT."""
    return max(narrowest, SMOOTHSTEP_SLOPE * abs(moved) / GRADIENT)


def fade_values(limit: float, unit: float, narrowest: float) -> np.ndarray:
    """(m,) increasing positive FAP values ending at `limit` where an ear table holds its
    fields: the largest value the narrowest fade serves, then doubling."""
    first = GRADIENT * narrowest / (SMOOTHSTEP_SLOPE * unit)
    values = [first]
    while values[-1] * 2.0 < limit:
        values.append(values[-1] * 2.0)
    values = [v for v in values if v < limit] + [limit]
    return np.array(values)


def smoothstep_fade(r: np.ndarray) -> np.ndarray:
    """1 - 3 r^2 + 2 r^3 over r clipped to [0, 1]: 1 at 0 (and below), 0 at 1 and beyond."""
    r = np.clip(r, 0.0, 1.0)
    return 1.0 - r * r * (3.0 - 2.0 * r)
