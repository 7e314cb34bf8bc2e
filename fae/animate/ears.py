"""The ears (FAPs 65-68) as FaceDefTables derived from the head, not simulated.

An ear is cartilage: FAP 65 raises the left ear, 67 pulls it sideways (66, 68 the right),
and it moves as a whole. Each ear FAP whose feature point (10.1-10.4) lies on the skin gets
a table that carries the ear rigidly by value x FAPU along the FAP's direction and fades
into the scalp around it, so the feature point moves exactly as the standard says and the
skin solver spends nothing on the ears (fae.sim simulates only skin near muscles).

The ear is the skin region of the feature point's triangle when that region's name says
"ear" (the generic head and every head adapted from it); around it the weight falls with
geodesic distance as Wendland's (1 - r)^4 (4 r + 1) over `FADE_ES` x ES0. On a head
without such a region the ear is the geodesic disc of `DISC_ES` x ES0 around the point.
A head's own (authored) FaceDefTable for an ear FAP takes precedence (the standard's
Predictable case); a table baked from the physics (fae.animate.bake) is this one's copy.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import dijkstra

from fae.animate.faptables import FAP_DIRECTION, FAP_FEATURE_POINT, FAP_LIMITS, fap_unit_scale
from fae.io.facemodel import FaceDefTable

EAR_FAPS = (65, 66, 67, 68)
FADE_ES = 0.2
DISC_ES = 0.5


def ear_tables(face, fapu: dict[str, float], graph) -> list[FaceDefTable]:
    """FaceDefTables (part "skin") of the ear FAPs of `face`; `graph` is the skin's (V, V)
    edge-length matrix (fae.animate.calibrate.edge_length_graph)."""
    own = {t.fap for t in face.face_def_tables if t.source == "authored"}  # a baked table is the physics' copy of these
    unit = fap_unit_scale(face)
    es0 = fapu["ES"] * 1024.0
    faces = np.asarray(face.skin_faces)
    names = list(face.region_names)
    region = np.asarray(face.skin_region)
    out = []
    for k in EAR_FAPS:
        point = face.feature_points.get(FAP_FEATURE_POINT[k - 1])
        if k in own or point is None or point.part != "skin":
            continue
        tri = faces[point.triangle]
        regions = {int(r) for r in region[tri]} if len(region) else set()
        if len(regions) == 1 and "ear" in names[regions.pop()]:
            ear = np.flatnonzero(region == region[tri[0]])
            fade = FADE_ES * es0
            d = dijkstra(graph, directed=False, indices=ear, limit=fade, min_only=True)
            r = np.clip(d / fade, 0.0, 1.0)
        else:
            disc = DISC_ES * es0
            d = dijkstra(graph, directed=False, indices=tri, limit=disc, min_only=True)
            r = np.clip(d / disc, 0.0, 1.0)
        w = (1.0 - r) ** 4 * (4.0 * r + 1.0)
        idx = np.flatnonzero(w > 1e-6)
        limit = float(np.abs(FAP_LIMITS[k - 1]).max())
        per_unit = w[idx, None] * (unit[k - 1] * FAP_DIRECTION[k - 1])[None, :]
        out.append(FaceDefTable(k, "skin", idx.astype(np.int32), np.array([-limit, 0.0, limit]),
                                np.stack([per_unit, per_unit])))
    return out
