"""FaceModel: one head, everything fae needs to animate it, as plain arrays.

The shipped template and every personalized head are the same kind of object (and the
same kind of .glb file, see docs/facemodel.md), so the player never cares where a head
came from. Units are SI: metres, radians. The face looks along +Z, y is up, and its own
left side is +x (MPEG-4 neutral face).

Surface points (feature points, muscle ends) are stored as (part, triangle, barycentric)
so that they follow any deformation or adaptation of the mesh they lie on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# The rigid frames that move at run time (a pose each per frame), and the rigid parts every
# head carries with the bone each one moves with.
BONES = ("head", "jaw", "eye_l", "eye_r", "tongue")
PART_BONES = {
    "cranium": "head",
    "upper_teeth": "head",
    "mandible": "jaw",
    "lower_teeth": "jaw",
    "tongue": "tongue",
    "eye_l": "eye_l",
    "eye_r": "eye_r",
}


@dataclass
class Part:
    """A rigid triangle mesh (bone, teeth, tongue, eyeball).

    vertices      (n, 3) float64, metres, rest pose in the face frame
    faces         (m, 3) int32, counter-clockwise seen from outside
    vertex_colors (n, 4) float32 linear RGBA in [0, 1], or None to use `color`
    color         (4,)   float32 linear RGBA base colour
    bone          which rigid frame moves it: "head", "jaw", "eye_l", "eye_r", "tongue"
    """

    vertices: np.ndarray
    faces: np.ndarray
    color: np.ndarray
    bone: str
    vertex_colors: np.ndarray | None = None


@dataclass
class SurfacePoint:
    """A point on a mesh: `part` is "skin" or a key of FaceModel.parts.

    triangle  index into that mesh's faces
    bary      (3,) float64 barycentric coordinates, summing to 1
    """

    part: str
    triangle: int
    bary: np.ndarray


@dataclass
class Muscle:
    """A Waters-style muscle.

    kind "linear": pulls skin from `insertion` towards `attachment` (on cranium or
        mandible). Zone of influence: a cone of half-angle `zone_angle` (rad) around the
        muscle axis at the attachment, full effect up to `fall_start` (m) from the
        attachment, fading to zero at `fall_end` (m).
    kind "sphincter": squeezes skin towards `attachment` (the centre, on the skin) inside
        an ellipse with semi-axes `semi_axes` (2,) metres along `axes` (2, 3) unit
        vectors (first: horizontal, second: vertical, in the face frame).
    regions: names of skin regions this muscle may move (keeps the upper-lip muscles
        off the lower lip and so on).
    """

    name: str
    kind: str
    attachment: SurfacePoint
    insertion: SurfacePoint | None
    regions: list[str]
    zone_angle: float = 0.0
    fall_start: float = 0.0
    fall_end: float = 0.0
    semi_axes: np.ndarray | None = None
    axes: np.ndarray | None = None


@dataclass
class FaceDefTable:
    """An MPEG-4 FaceDefTable entry: how one FAP displaces vertices of one mesh.

    fap           FAP number (3..68)
    part          "skin" or a part name
    vertices      (k,) int32 vertex indices in that mesh
    borders       (m + 1,) float64 FAP-value interval borders, increasing, containing 0
    displacements (m, k, 3) float64 metres per FAP unit within each interval
    source        "authored": a motion of its own, added to whatever else moves the mesh;
                  "physics": baked from this head's simulation (fae.animate.bake), the
                  motion the simulation itself gives, so the simulating player leaves it out
    """

    fap: int
    part: str
    vertices: np.ndarray
    borders: np.ndarray
    displacements: np.ndarray
    source: str = "authored"


FACE_DEF_TABLE_SOURCES = ("authored", "physics")


@dataclass
class FaceModel:
    """A head ready to animate.

    skin_vertices   (V, 3) float64, metres: the epidermis at rest (neutral face)
    skin_faces      (F, 3) int32
    skin_uv         (V, 2) float32 texture coordinates in [0, 1]
    skin_color      (4,)   float32 linear RGBA
    skin_mirror     (V,)   int32: index of each vertex's mirror partner (x -> -x)
    skin_region     (V,)   int32: index into `region_names`
    region_names    list of region names ("lip_upper", "lip_lower", "chin", ...)
    skin_thickness  (V,)   float64, metres: soft-tissue depth below each skin vertex
    layer_params    scalar parameters for building the 3-layer skin (names and units in
                    docs/facemodel.md), e.g. {"layer_depths": [...], ...}
    parts           rigid meshes by name, see PART_BONES
    jaw_pivot       (3,) metres: a point on the mandible's hinge axis
    jaw_axis        (3,) unit vector of the hinge axis (about +x)
    eye_centers     {"eye_l": (3,), "eye_r": (3,)} metres, eyeball rotation centres
    feature_points  MPEG-4 FDP name ("2.1", ...) -> SurfacePoint
    muscles         list of Muscle
    face_def_tables list of FaceDefTable (may be empty)
    fap_mapping     arrays the runtime derives by probing this head (FAP -> controls);
                    opaque to io, stored as-is; empty until calibrated
    scan_transform  (4, 4) float64: maps this model's face frame back to the frame and
                    unit of the scan it was adapted to (identity for the template)
    skin_texture    (H, W, 3) uint8 sRGB colour image of the skin, or None (then the skin
                    is drawn in `skin_color`); texel row r, column c lies at skin_uv
                    ((c + 0.5) / W, (r + 0.5) / H): glTF's convention, v = 0 on the first row
    meta            free JSON-serializable metadata ("name", "generator", ...)
    """

    skin_vertices: np.ndarray
    skin_faces: np.ndarray
    skin_uv: np.ndarray
    skin_color: np.ndarray
    skin_mirror: np.ndarray
    skin_region: np.ndarray
    region_names: list[str]
    skin_thickness: np.ndarray
    layer_params: dict
    parts: dict[str, Part]
    jaw_pivot: np.ndarray
    jaw_axis: np.ndarray
    eye_centers: dict[str, np.ndarray]
    feature_points: dict[str, SurfacePoint]
    muscles: list[Muscle]
    face_def_tables: list[FaceDefTable] = field(default_factory=list)
    fap_mapping: dict[str, np.ndarray] = field(default_factory=dict)
    scan_transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    meta: dict = field(default_factory=dict)
    skin_texture: np.ndarray | None = None

    @property
    def skin_vertex_count(self) -> int:
        return int(self.skin_vertices.shape[0])

    def mesh(self, part: str) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (n, 3) metres, faces (m, 3)) of "skin" or a part."""
        if part == "skin":
            return self.skin_vertices, self.skin_faces
        p = self.parts[part]
        return p.vertices, p.faces

    def surface_point_position(self, point: SurfacePoint, vertices: np.ndarray | None = None) -> np.ndarray:
        """(3,) metres: where `point` lies on its mesh (or on `vertices`, a deformed copy of it)."""
        verts, faces = self.mesh(point.part)
        if vertices is not None:
            verts = vertices
        tri = verts[faces[point.triangle]]
        return np.asarray(point.bary, dtype=np.float64) @ tri

    def feature_point_positions(self) -> dict[str, np.ndarray]:
        """FDP name -> (3,) metres at rest."""
        return {name: self.surface_point_position(p) for name, p in self.feature_points.items()}
