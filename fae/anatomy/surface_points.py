"""Surface points of the template's meshes: at a vertex, or the closest to a target.

    vertex_point(part, F, vertex) -> SurfacePoint
    closest_point(part, V, F, target) -> SurfacePoint
    chin_contour_point(face) -> (3,)      the chin's lowest point, where markups put "2.1"
    markup_positions(face) -> {FDP: (3,)}  feature points as scan and photo markups place them
"""

from __future__ import annotations

import numpy as np

from fae.anatomy.geometry import closest_surface_points
from fae.io.facemodel import SurfacePoint


def vertex_point(part: str, F: np.ndarray, vertex: int) -> SurfacePoint:
    """SurfacePoint exactly at `vertex`, on the lowest-numbered face that uses it."""
    tri = int(np.flatnonzero((F == vertex).any(axis=1))[0])
    bary = (F[tri] == vertex).astype(np.float64)
    return SurfacePoint(part=part, triangle=tri, bary=bary)


def closest_point(part: str, V: np.ndarray, F: np.ndarray, target) -> SurfacePoint:
    """SurfacePoint closest to `target` (3,) on mesh (V, F) (same unit as V)."""
    _, tri, bary = closest_surface_points(V, F, np.asarray(target, dtype=np.float64)[None])
    b = np.clip(bary[0], 0.0, None)
    return SurfacePoint(part=part, triangle=int(tri[0]), bary=b / b.sum())


MIDLINE = 0.002  # metres: skin this close to the face's mid-plane is on its midline


def chin_contour_point(face) -> np.ndarray:
    """(3,) metres: the lowest midline point of the chin region of a FaceModel's skin (the
    bottom of the face's outline seen from the front), or its feature point 2.1 when it has
    no chin region. Under a nearly level chin this lies well behind 2.1, the chin's
    front-bottom (fae.anatomy.template): it is where landmark markups put the "bottom of
    the chin" (iBUG's contour point 8 sits under the chin) and where the head ends."""
    V = np.asarray(face.skin_vertices, dtype=np.float64)
    names = list(face.region_names)
    if "chin" in names:
        chin = np.flatnonzero((np.asarray(face.skin_region) == names.index("chin")) & (np.abs(V[:, 0]) < MIDLINE))
        if len(chin):
            return V[chin[np.argmin(V[chin, 1])]].copy()
    return face.feature_point_positions()["2.1"]


def markup_positions(face) -> dict[str, np.ndarray]:
    """FDP name -> (3,) metres: the face's feature points as landmark markups place them on
    it (2.1 at `chin_contour_point`), to pair with a scan's or a photo's markup."""
    out = face.feature_point_positions()
    if "2.1" in out:
        out["2.1"] = chin_contour_point(face)
    return out
