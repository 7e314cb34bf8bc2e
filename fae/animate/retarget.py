"""Any mesh animated by the template's motion: motion-vector transfer (paper 002 §3).

A head fae did not make (an artist's model, a game character, a scan nobody wants
re-topologized) keeps its own vertices, faces and UVs. The template is played as usual
(physics or FaceDefTables, fae.animate.player) and each frame its skin's motion vectors are
carried over to the target:

    target = read_target("bust.obj", "bust_landmarks.json")   # mesh + MPEG-4 feature points
    rt = retarget(template, target)                            # once: seconds (a fit)
    player = RetargetPlayer(rt, Player(playable_head(template)))
    for f in player.play(stream): f.skin_vertices, f.bone_transforms   # the target's

Once per target (`retarget`): the template is fitted to the target from its feature
points exactly as `fae adapt` fits it to a scan (fae.adapt.workflow.adapt_scan, without the
face-landmark model: the feature points given stand in for it), which is a far denser
correspondence than an RBF through a few dozen points. Each target vertex is bound to the
closest point of the fitted skin on the template's faces (the fitted head's own flip a
few upper-lid caps; the motion carried lives on the template's), so that point is also a
point of the template. Where
neighbours on the target bind to points far apart on the template (either side of a
crease), their bindings are averaged over the target's mesh (smoothed_across_jumps): the
menpo3d mask's fold lines along its creases went, and its folded share halved. Where the
target is finer than the template (more than 1.4 of its vertices bound per template
triangle: the mask's 3-27, the template bound to itself 0.4-1.3), every vertex's binding is
averaged with its neighbours' over a few of its own short edges (smoothed_where_fine): the
template's piecewise-linear motion, read through a binding that jitters from vertex to
vertex, folded the mask's 1 mm triangles at the mouth corners of a smile and over lowered
brows (its folded share 0.43 -> 0.24 %, every FAP as before); a target as coarse as the
template keeps its bindings. An eye carved into the target's skin (no eyeball piece) is
bound between the lids' margins and closes under the upper one as a curtain
(carved_eye_rows), eye by eye where that folds less at the template's own blink. Per template
vertex a 3x3 T = R_fit S R_template^T (fae.adapt.binding.frame_transforms: the paper's
local frames and box scales, eq. 5-9) turns a motion vector of the template into one of
the fitted skin, i.e. of the target; a smooth per-axis factor over the target's skin
(fapu_gain_field) then pins the motion of each FAP's feature point to value x the target's
own FAPU, as the standard defines it (the lids' and lips' from the template's own motion
for each of their FAPs, settled at half its range, the others' from a uniform one). Motion
fades to zero where the target extends beyond
what the template covers (shoulders, plinth, hair: COVERAGE_NEAR..COVERAGE_FAR metres from
the fitted skin). The target's separate pieces that sit on the fitted head's eyeballs,
teeth or tongue (pieces under PART_SIZE_SHARE of the size of the face's piece, the one
the feature points lie on, however finely meshed) become rigid parts moved by the
template's eye, head, jaw and tongue bones, re-anchored at the fitted head's eye centres, jaw hinge and 7.1.

Per frame (`RetargetPlayer.step`): the head pose is taken off the template's skin, the
displacement from its neutral skin gathered (one batched 3x3 product over the template
vertices in use and one sparse (k, u) product), added to the target's rest, and the head
pose, re-anchored, put back (faded like the motion, except above the chin, where what the
template does not reach, a hat or hair off the scalp, turns with the head as one body). A
neutral frame gives the target's rest exactly. tools/bench_retarget.py measures the transfer's frames per second.

The target is held as a FaceModel in the face frame (metres; `model.scan_transform` maps
back to the file's frame and unit), with the template's regions read off the binding and
the MPEG-4 feature points placed on its own surface: those given, and the others read off
the fit, each projected onto the target's triangles of its own region (an inner-lip point
on the lip it belongs to). So `fae.animate.verify.verify_faps(RetargetPlayer(...))`
measures the target's own FAP response against value x the target's FAPU.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.sparse as sp

from fae.adapt.binding import (bind_to_surface, coverage_weights, frame_transforms, gather_matrix,
                               pinned_to_points, seam_groups, welded_components)
from fae.cores import workers
from fae.io.facemodel import BONES, FaceModel, Part, SurfacePoint
from fae.mesh import vertex_normals

MIN_FEATURE_POINTS = 8  # usable feature points of the template's skin a target must have
INSIDE_OUT_SHARE = 0.5  # of a target's surface facing into the head: wound inside out, turned (and
# fitted again: the first fit, paired by the wrong normals, leaves some of it facing out: 0.89-0.98)
MIXED_WINDING_SHARE = 0.1  # ... beyond this after any turning: windings mixed, refused
COVERAGE_NEAR = 0.004  # metres from the fitted skin within which a target vertex moves fully
COVERAGE_FAR = 0.015  # metres from it beyond which a target vertex does not move at all
RIGID_PARTS = ("eye_l", "eye_r", "upper_teeth", "lower_teeth", "tongue")
PART_SIZE_SHARE = 0.5  # a piece at least this share of the face piece's size is skin (an eyeball 0.1, teeth 0.2)
PART_REACH = 0.3  # a piece is a part when its median distance to it is below this share of its size
PART_REACH_MIN = 0.002  # ... or below this many metres
PIN_REACH = 0.03  # metres around the given feature points within which the fit is moved onto them
FDP_REGION_REACH = 0.006  # metres: a feature point looks this far for triangles of its own region
GAIN_REACH = 0.03  # metres around the FAPs' feature points over which their FAPU gains spread
GAIN_LIMITS = (0.05, 4.0)  # the least and most a FAPU gain scales the carried motion by
# FAPs whose FAPU gain comes from their own motion (fapu_gain_field), settled at half range
# where verify-faps measures it: the eyelids, whose points on a mask with the eyes nearly
# shut bind where the lid's motion differs from that at the template's point (menpo3d's
# lower lids at 1.43x with a uniform motion's gain), and the lips, whose points and their
# twins are one point of the template and several millimetres apart on a target (menpo3d's
# inner and outer mouth corners, 6 mm), both beside the template's corner where its motion
# falls off (its corners' stretch at 0.57-0.69x with a uniform motion's gain; with the
# template's linear motion at rest instead of the settled one, 1.3-1.6x); and the nose
# wings, whose points sit in the alar crease, where the binding is averaged (a uniform
# motion's gain left them at 0.54-0.63x on the mask)
MOTION_GAIN_FAPS = (19, 20, 21, 22) + tuple(range(4, 14)) + tuple(range(51, 61)) + (61, 62)
SETTLE_FRAMES = 30  # frames of 1/25 s to settle each (within 1 % of verify-faps' 60 on the generic head)
SETTLE_THREADS = 4  # at most, settling side by side
NECK_FADE = (0.02, 0.09)  # metres below the chin (2.1) where the head pose starts and ends fading out
ABOVE_CHIN = (0.0, 0.02)  # metres below the chin over which the head pose of what the fit does not reach fades out
PIECE_REACH = 0.03  # metres: a piece this close to the fitted skin sits on the head (a hat) and turns with it
# a carved eye open at least this share of the template's (fitted between its lids, which
# close as a curtain); one opened less (the menpo3d mask's, a tenth) is shut, its lids bound as they lie
CARVED_EYE_OPEN = 0.5


class RetargetError(ValueError):
    """A target that cannot be animated; the message names the file and what was expected."""


@dataclass
class TargetMesh:
    """A mesh to animate, as read.

    path       where it came from (for messages)
    vertices   (n, 3) float64 in the file's frame and unit
    faces      (m, 3) int64
    uv         (n, 2) float32 texture coordinates as in the file (v = 0 at the image's
               bottom row, OBJ's convention), or None when the file has none
    landmarks  MPEG-4 feature point name -> (3,) in the file's frame and unit
    landmarks_path  the feature points' file (for messages)
    texture    (H, W, 3) uint8 sRGB colour image of its material, or None
    texture_missing  the colour image an OBJ's material names but that could not be read
               (missing, corrupt), or None: the mesh is drawn untextured
    """

    path: str
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None
    landmarks: dict[str, np.ndarray]
    landmarks_path: str = "--landmarks"
    texture: np.ndarray | None = None
    texture_missing: str | None = None


def _named_texture(path: str) -> str | None:
    """The colour image (map_Kd) an OBJ's material library names, as a path, or None."""
    if not path.lower().endswith(".obj"):
        return None
    folder = os.path.dirname(os.path.abspath(path))
    try:
        with open(path, "r", errors="replace") as f:
            libraries = [key_rest[1].strip() for key_rest in (line.split(None, 1) for line in f)
                         if len(key_rest) == 2 and key_rest[0] == "mtllib"]
        for lib in libraries:
            with open(os.path.join(folder, lib), "r", errors="replace") as f:
                for line in f:
                    if line.strip().startswith("map_Kd "):
                        return os.path.join(folder, line.strip().split()[-1])
    except (OSError, IndexError):
        return None
    return None


def _read_surface(path: str, n: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The mesh file's texture coordinates (n, 2) float32 as the file has them (v = 0 at the
    image's bottom row), when it has one per vertex, and its colour texture (H, W, 3) uint8
    sRGB when its material has one (an OBJ's map_Kd, a glTF's base colour; trimesh packs a
    file's several materials into one image); None for what it lacks."""
    try:
        import trimesh

        from fae.io.scan import mesh_source

        source, how = mesh_source(path)
        visual = getattr(trimesh.load(source, force="mesh", process=False, **how), "visual", None)
        uv = getattr(visual, "uv", None)
    except Exception:
        return None, None
    if uv is None or len(uv) != n:
        return None, None
    try:
        material = getattr(visual, "material", None)
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        texture = None if image is None else np.asarray(image.convert("RGB"), dtype=np.uint8)
    except Exception:  # a texture that cannot be read leaves the mesh untextured, as one without
        texture = None
    if texture is not None and (texture.ndim != 3 or min(texture.shape[:2]) < 1):
        texture = None
    return np.asarray(uv, dtype=np.float32), texture


def _is_facemodel(path: str) -> bool:
    """Whether `path` is a .glb that fae wrote as a FaceModel (its extension declared)."""
    if not path.lower().endswith(".glb"):
        return False
    try:
        import pygltflib

        from fae.io.facemodel_gltf import EXTENSION

        return EXTENSION in (pygltflib.GLTF2.load(path).extensionsUsed or [])
    except Exception:  # not readable as glTF: read_scan says why
        return False


def read_target(mesh_path: str | os.PathLike, landmarks_path: str | os.PathLike) -> TargetMesh:
    """The mesh (any format fae.io.scan.read_scan reads) and its feature points (any format
    fae.io.scan.read_landmarks reads: FDP JSON or CSV, menpo .ljson / CSV with iBUG-68).
    Raises RetargetError naming the file and what was expected."""
    from fae.io.scan import LandmarkError, indexed_vertices, read_landmarks, read_scan

    mesh_path, landmarks_path = os.fspath(mesh_path), os.fspath(landmarks_path)
    if _is_facemodel(mesh_path):
        raise RetargetError(f"{mesh_path}: is a fae head (FaceModel); play it with --head {mesh_path} and no "
                            "--landmarks (motion transfer would take its skull and jaw for skin)")
    try:
        V, F = read_scan(mesh_path)
    except (OSError, ValueError) as exc:
        raise RetargetError(str(exc)) from None
    try:
        landmarks = read_landmarks(landmarks_path, lambda: indexed_vertices(mesh_path, V))
    except (OSError, LandmarkError, ValueError) as exc:
        raise RetargetError(str(exc)) from None
    uv, texture = _read_surface(mesh_path, len(V))
    named = _named_texture(mesh_path) if texture is None and uv is not None else None
    return TargetMesh(mesh_path, V, F, uv, landmarks, landmarks_path, texture, named)


def usable_landmarks(template: FaceModel, landmarks: dict[str, np.ndarray]) -> list[str]:
    """Names of the given feature points the template has on its skin, with finite positions."""
    return [n for n, p in landmarks.items() if n in template.feature_points
            and template.feature_points[n].part == "skin" and np.all(np.isfinite(p))]


@dataclass
class Retarget:
    """What a target needs per frame, computed once (see the module docstring).

    model          the target as a FaceModel in the face frame (skin: its pieces that are
                   not rigid parts; parts: the rigid ones), feature points on its surface
    skin_index     (k,) int64: the target vertex of each model skin vertex
    part_index     part name -> (j,) int64 target vertices of that part
    used           (u,) int64 template skin vertices whose motion reaches the target
    frame_transform (u, 3, 3) T of those vertices (template motion -> fitted skin's)
    gather         (k, u) CSR: coverage weight x barycentric coordinates of each skin
                   vertex's bound point
    coverage       (k,) in [0, 1]: how fully each skin vertex follows (1: on the fitted skin)
    fapu_gain      (k, 3) the factor, per skin vertex and face axis (x, y, z), that pins the
                   carried motion's magnitude to the target's FAPU (fapu_gain_field)
    head_weight    (k,) in [0, 1]: how fully each skin vertex turns with the head pose: the
                   coverage, and fully above the chin (2.1; fading over ABOVE_CHIN below it)
                   wherever the coverage is less on a piece that touches the head (a hat,
                   hair off the scalp; PIECE_REACH), fading down
                   the neck (NECK_FADE below the chin) so that a bust's shoulders and chest
                   stay put
    anchors        bone -> ((3,) template point, (3,) target point) its poses are re-anchored at
    scale          the target's size over the template's (FAPU ratio, mean of ES, ENS, MNS, MW)
    report         what was found and measured (fit errors, scales, parts, feature points)
    normal_groups  (k,) int64: skin vertices that are one point of the surface split along a
                   texture seam share a label (fae.adapt.binding.seam_groups; FaceRenderer)
    loose          ((j,) int64 target vertices no triangle uses, (j, 3) their rest in the face
                   frame): they stay where they are
    """

    model: FaceModel
    skin_index: np.ndarray
    part_index: dict[str, np.ndarray]
    used: np.ndarray
    frame_transform: np.ndarray
    gather: sp.csr_matrix
    coverage: np.ndarray
    anchors: dict[str, tuple[np.ndarray, np.ndarray]]
    scale: float
    report: dict = field(default_factory=dict)
    vertex_count: int = 0
    normal_groups: np.ndarray | None = None
    head_weight: np.ndarray | None = None
    fapu_gain: np.ndarray | None = None
    loose: tuple[np.ndarray, np.ndarray] | None = None

    def displacements(self, template_motion: np.ndarray) -> np.ndarray:
        """(k, 3) metres: the target skin's motion for the template skin's motion
        (u, 3) at the vertices `used` (face frame, head pose taken off), times the FAPU
        gains (`fapu_gain`) where set."""
        turned = np.einsum("uij,uj->ui", self.frame_transform, template_motion)
        out = self.gather @ turned
        return out if self.fapu_gain is None else out * self.fapu_gain

    def bone_pose(self, bone: str, template_pose: np.ndarray, head: np.ndarray | None = None) -> np.ndarray:
        """(4, 4) the target's pose of `bone` for the template's `template_pose` (rest -> now,
        face frame): the same rotation about the target's own anchor, translations scaled.
        head: the template's head pose, when template_pose includes it (every bone but
        "head"): the bone's own motion is re-anchored at its anchor, the head's at 7.1's."""
        if head is None:
            return _reanchored(template_pose, *self.anchors[bone], self.scale)
        own = np.linalg.solve(head, template_pose)
        return _reanchored(head, *self.anchors["head"], self.scale) @ \
            _reanchored(own, *self.anchors[bone], self.scale)

    def target_vertices(self, skin: np.ndarray, bones: dict[str, np.ndarray], frame: str = "face") -> np.ndarray:
        """(n, 3) every vertex of the target, in its own order: skin positions (k, 3) and the
        rigid parts under `bones` (the target's poses), in the face frame (metres) or, with
        frame="file", in the target file's frame and unit."""
        from fae.adapt.calibration import apply_transform

        out = np.zeros((self.vertex_count, 3))
        if self.loose is not None:
            out[self.loose[0]] = self.loose[1]
        out[self.skin_index] = skin
        for name, idx in self.part_index.items():
            part = self.model.parts[name]
            M = bones.get(part.bone, np.eye(4))
            out[idx] = part.vertices @ M[:3, :3].T + M[:3, 3]
        return apply_transform(self.model.scan_transform, out) if frame == "file" else out


def fapu_gain_field(model: FaceModel, carried: Callable[[np.ndarray], np.ndarray], template_fapu: dict[str, float],
                    target_fapu: dict[str, float], reach: float = GAIN_REACH,
                    fap_motion: dict[int, tuple[np.ndarray, float]] | None = None) -> tuple[np.ndarray, dict]:
    """(k, 3) the factor per target skin vertex (model.skin_vertices (k, 3), face frame) and
    face axis by which the carried motion is scaled, and per feature point the factors met.

    The standard moves a FAP's feature point by value x the head's FAPU; the local frames'
    box scales (the paper's magnitude adjustment) follow the target's shape, which differs
    from its FAPU wherever the target is shaped otherwise than the template: eyes nearly
    shut (an iris diameter a tenth of the template's), a lip thicker, a jaw longer. At each
    feature point a FAP moves, per axis it moves along: gain = what a uniform template
    motion along that axis becomes there along the same axis (carried: (3,) face-frame
    motion -> (k, 3) target motion, without any gain field), and factor = (target FAPU /
    template FAPU of that FAP's unit) / gain, clamped to GAIN_LIMITS (a gain <= 0, an axis
    the frames turn over, gives none); an axis no FAP of the point moves along takes the
    geometric mean of those that do. With `fap_motion` (FAP k -> (u, 3) the template's
    motion for one unit of k at the vertices used, and how far that moves the template's
    own point along k's direction), a FAP it holds takes its gain from that motion instead
    of a uniform one: gain = what the carried motion moves the target's point along k's
    direction over what it moves the template's, so a point that binds where the template's
    motion is larger or smaller than at the template's own point still moves by value x
    its FAPU. The factor scales the whole motion along its face
    axis, including what the frames turn into it from the others. Between the points the
    log-factors spread as the smoothest field over the target's surface that meets them
    (softly: fae.adapt.binding.pinned_to_points, along the skin, never across the mouth's
    slit), fading to 1 beyond `reach` metres of every point, and kept between the smallest
    and largest factor met and 1."""
    from fae.mpeg4.faptables import FAP_DIRECTION, FAP_FEATURE_POINT, FAP_UNIT_NAME, SKIN_TRANSLATION_FAPS

    V = np.asarray(model.skin_vertices, dtype=np.float64)
    F = np.asarray(model.skin_faces, dtype=np.int64)
    uniform = [carried(axis) for axis in np.eye(3)]  # (k, 3) each
    logs: dict[str, dict[int, list[float]]] = {}
    for k in SKIN_TRANSLATION_FAPS:
        name = FAP_FEATURE_POINT[k - 1]
        point = model.feature_points.get(name)
        unit = FAP_UNIT_NAME[k - 1]
        if point is None or point.part != "skin" or unit not in template_fapu or unit not in target_fapu:
            continue
        axis = int(np.argmax(np.abs(FAP_DIRECTION[k - 1])))
        corners = F[point.triangle]
        gain = float(point.bary @ uniform[axis][corners, axis])
        if fap_motion is not None and k in fap_motion and fap_motion[k][1] > 0.0:
            motion, own = fap_motion[k]
            moved = float(point.bary @ carried(motion)[corners] @ FAP_DIRECTION[k - 1]) / own
            gain = moved if moved > 0.0 else gain  # carried the wrong way: the uniform motion's
        if not gain > 0.0:  # the frames turn this axis over here: no magnitude to correct
            continue
        factor = np.clip(target_fapu[unit] / template_fapu[unit] / gain, *GAIN_LIMITS)
        logs.setdefault(name, {}).setdefault(axis, []).append(float(np.log(factor)))
    names = sorted(logs)
    if not names:
        return np.ones_like(V), {}
    met = np.zeros((len(names), 3))
    for i, name in enumerate(names):
        axes = {a: float(np.mean(v)) for a, v in logs[name].items()}
        fill = float(np.mean(list(axes.values())))
        met[i] = [axes.get(a, fill) for a in range(3)]
    faces = np.array([model.feature_points[n].triangle for n in names])
    bary = np.array([model.feature_points[n].bary for n in names])
    at = np.einsum("kj,kjd->kd", bary, V[F[faces]])
    field_ = pinned_to_points(V, F, faces, bary, at + met, reach) - V
    # the smoothest field overshoots between points of unlike factors (a lid's 0.1 beside a
    # brow's 0.9): kept within the factors met and 1
    field_ = np.clip(field_, np.minimum(met.min(axis=0), 0.0), np.maximum(met.max(axis=0), 0.0))
    return np.exp(field_), {n: np.exp(met[i]).round(4).tolist() for i, n in enumerate(names)}


def _playable_template(template: FaceModel):
    """The template's PlayableHead, or None when it has no FAP mapping of its own (playing it
    would first calibrate it, tens of seconds)."""
    from fae.animate.player import needs_calibration, playable_head

    if not template.fap_mapping or "gain_pos" not in template.fap_mapping or needs_calibration(template):
        return None
    return playable_head(template)


def _template_fap_motion(template: FaceModel, used: np.ndarray, head) -> dict[int, tuple[np.ndarray, float]]:
    """FAP k -> ((u, 3) the template skin's motion per unit of k at the vertices `used`,
    metres, as settled with k alone at half its range (where verify-faps measures it; the
    linear response at rest left the lids' margins, which stop on the eyeball, 20-25 %
    short on a target that binds there); how far it moves the template's own feature point
    of k along k's direction) for the lids', lips' and nose wings' FAPs (MOTION_GAIN_FAPS);
    head: the template's PlayableHead (_playable_template), None (no mapping): empty."""
    from fae.mpeg4.faptables import FAP_DIRECTION, FAP_FEATURE_POINT, FAP_LIMITS
    from fae.animate.player import Player
    from fae.animate.verify import settled_skin

    faps = [k for k in MOTION_GAIN_FAPS if FAP_FEATURE_POINT[k - 1] in template.feature_points
            and template.feature_points[FAP_FEATURE_POINT[k - 1]].part == "skin" and FAP_LIMITS[k - 1, 1] > 0]
    if head is None or not faps:
        return {}
    rest = np.asarray(template.skin_vertices, dtype=np.float64)
    local = threading.local()  # a Player per thread, all on the one head

    def settled_motion(k: int) -> tuple[np.ndarray, float]:
        if not hasattr(local, "player"):
            local.player = Player(head)
        values = np.zeros(68)
        values[k - 1] = FAP_LIMITS[k - 1, 1] / 2.0
        motion = (settled_skin(local.player, values, max_frames=SETTLE_FRAMES) - rest) / values[k - 1]
        # the point's own displacement (its barycentric blend of the field)
        own = float(template.surface_point_position(template.feature_points[FAP_FEATURE_POINT[k - 1]], motion)
                    @ FAP_DIRECTION[k - 1])
        return motion[used], own

    # the settles do not depend on each other, and Warp's CPU kernels release the GIL
    with ThreadPoolExecutor(workers(SETTLE_THREADS)) as pool:
        return dict(zip(faps, pool.map(settled_motion, faps)))


def _reanchored(M: np.ndarray, a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """A M A^-1 with A: x -> s (x - a) + b (the pose M moved from anchor a to b, scaled by s)."""
    A = np.eye(4)
    A[:3, :3] *= s
    A[:3, 3] = b - s * a
    Ainv = np.eye(4)
    Ainv[:3, :3] /= s
    Ainv[:3, 3] = a - b / s
    return A @ M @ Ainv


def _sub_mesh(F: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index (k,) of the kept vertices, faces (f, 3) renumbered into them): the triangles
    of F whose corners are all kept."""
    index = np.flatnonzero(keep)
    new = np.full(len(keep), -1, dtype=np.int64)
    new[index] = np.arange(len(index))
    faces = np.asarray(F, dtype=np.int64)
    faces = faces[keep[faces].all(axis=1)]
    return index, new[faces]


def _fapu_ratio(template: dict[str, float], target: dict[str, float]) -> float:
    return float(np.mean([target[k] / template[k] for k in ("ES", "ENS", "MNS", "MW")]))


def _on_region(V: np.ndarray, F: np.ndarray, same_region: np.ndarray, tri_region: np.ndarray, region: int,
               p: np.ndarray, cache: dict) -> tuple[int, np.ndarray, float] | None:
    """(triangle, bary, distance) of the closest point to p (3,) on the triangles of F whose
    corners all lie in `region`, or None when there are none."""
    from fae.adapt.query import MeshQuery

    key = (id(V), region)
    if key not in cache:
        faces = np.flatnonzero(same_region & (tri_region[:, 0] == region))
        cache[key] = (MeshQuery(V, F[faces]) if len(faces) else None, faces)
    q, faces = cache[key]
    if q is None:
        return None
    _, d, f, b = q.closest_points(p[None])
    return int(faces[f[0]]), b[0], float(d[0])


def _target_feature_points(template: FaceModel, fitted: FaceModel, given: dict[str, np.ndarray],
                           skin_V: np.ndarray, skin_U: np.ndarray, skin_F: np.ndarray, skin_region: np.ndarray,
                           parts: dict[str, tuple[str, np.ndarray, np.ndarray]]
                           ) -> tuple[dict[str, SurfacePoint], dict[str, str]]:
    """Feature points on the target: a given one (face frame) where it was given, projected
    onto the target's skin; any other, the target's point bound closest to the template's
    own (skin_U (k, 3): where each target skin vertex is bound on the template at rest), so
    that it moves as the template's does. Either within the triangles of the point's own
    template region where any lie within FDP_REGION_REACH (an inner-lip point stays on its
    lip). Points of the template's parts go on the target's part of that name, or, for the
    pupils (needed for ES), onto the skin (a sculpted eye); a point bound nowhere near the
    target (a crown above a face mask) is left out. Returns the points and, per name,
    "given" or "fit"."""
    from fae.adapt.query import MeshQuery

    fitted_at = fitted.feature_point_positions()
    rest_at = template.feature_point_positions()
    skin_q = MeshQuery(skin_V, skin_F)
    pulled_q = MeshQuery(skin_U, skin_F)
    tri_region = skin_region[skin_F]
    same = (tri_region == tri_region[:, :1]).all(axis=1)
    cache: dict = {}
    out, source = {}, {}
    for name, sp_ in template.feature_points.items():
        if sp_.part != "skin":
            target_part = next((k for k, (src, _, _) in parts.items() if src == sp_.part), None)
            if target_part is not None:
                _, PV, PF = parts[target_part]
                _, _, f, b = MeshQuery(PV, PF).closest_points(fitted_at[name][None])
                out[name], source[name] = SurfacePoint(target_part, int(f[0]), b[0]), "fit"
            elif name in ("3.5", "3.6"):
                _, _, f, b = skin_q.closest_points(fitted_at[name][None])
                out[name], source[name] = SurfacePoint("skin", int(f[0]), b[0]), "fit"
            continue
        tri = template.skin_faces[sp_.triangle]
        region = int(template.skin_region[tri[int(np.argmax(sp_.bary))]])
        V, q, p = (skin_V, skin_q, given[name]) if name in given else (skin_U, pulled_q, rest_at[name])
        hit = _on_region(V, skin_F, same, tri_region, region, p, cache)
        if hit is None or hit[2] > FDP_REGION_REACH:
            _, d, f, b = q.closest_points(p[None])
            if name not in given and d[0] > FDP_REGION_REACH:
                continue
            hit = (int(f[0]), b[0], float(d[0]))
        out[name] = SurfacePoint("skin", hit[0], hit[1])
        source[name] = "given" if name in given else "fit"
    return out, source


JUMP_STRETCH = 2.5  # a target edge whose ends bind this many times its length apart on the template jumps
JUMP_RINGS = 2  # rings around a jump whose rows are averaged with their neighbours'
JUMP_ROUNDS = 3  # rounds of that averaging
OPENING_RINGS = 1  # rings around an edge across a shut opening whose rows are averaged (2 reached past
# Demosthenes' carved lips into his moustache, which folded as the upper lip rose)
# target vertices bound per template triangle around a binding: not fine (the template
# bound to itself has at most 1.33) .. fully fine
FINE_DENSITY = (1.4, 2.0)
FINE_SHARE = 0.5  # of the template's local edge: target edges this long weigh exp(-1) in the averaging
FINE_ROUNDS = 3  # rounds of that averaging
FINE_LEAST = 0.02  # weights below this are left out (the rows stay as sparse as they can)


def _rows_averaged(G: sp.csr_matrix, Y: np.ndarray, F: np.ndarray, groups: np.ndarray | None, rounds: int,
                   step_of: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], sp.csr_matrix | None]
                   ) -> sp.csr_matrix:
    """G (k, m) with its rows, as barycentric coordinates, replaced `rounds` times by
    step @ rows, then scaled by each row's own coverage (its sum) again: every row keeps its
    coverage, so a neutral frame still gives the rest exactly and a vertex that does not
    follow stays still. step = step_of(edges (e, 2) between points, each once, Yg (p, 3) the points,
    covered (p,) bool, first (p,) the first vertex of each point), (p, p) with rows summing to
    one, None: G as it is. groups (k,): vertices split along a texture seam (one label per
    point) are one point, and share its row."""
    from fae.mesh import edges as unique_edges

    g = np.arange(len(Y)) if groups is None else np.asarray(groups, dtype=np.int64)
    _, first, point = np.unique(g, return_index=True, return_inverse=True)  # one row per point
    edges = unique_edges(point[np.asarray(F, dtype=np.int64)].reshape(-1, 3))
    edges = edges[edges[:, 0] != edges[:, 1]]  # a triangle welded flat at a seam joins a point to itself
    G = G.tocsr()[first]
    coverage = np.asarray(G.sum(axis=1)).ravel()
    step = step_of(edges, Y[first], coverage > 0.0, first)  # edges: each once
    if step is None:
        return G[point].tocsr()
    out = sp.diags(np.where(coverage > 0.0, 1.0 / np.maximum(coverage, 1e-300), 0.0)) @ G  # barycentric rows
    for _ in range(rounds):
        out = (step @ out).tocsr()
    out = (sp.diags(coverage) @ out)[point].tocsr()
    out.eliminate_zeros()
    return out


# the template's openings: skin either side of each moves apart (a mouth, an eye opening)
OPENINGS = (("lip_upper", "lip_lower"), ("eyelid_upper_l", "eyelid_lower_l"), ("eyelid_upper_r", "eyelid_lower_r"))


def opening_sides(region_names, region: np.ndarray) -> np.ndarray:
    """(k,) int per target vertex, from the template region (k,) (an index into
    region_names) of the corner nearest its binding: 2i + 1 on the first side of
    OPENINGS[i], 2i + 2 on its second, 0 elsewhere."""
    names = list(region_names)
    nearest = np.asarray(region)
    out = np.zeros(len(nearest), dtype=np.int64)
    for i, pair in enumerate(OPENINGS):
        for j, name in enumerate(pair):
            if name in names:
                out[nearest == names.index(name)] = 2 * i + 1 + j
    return out


def smoothed_across_jumps(G: sp.csr_matrix, U: np.ndarray, Y: np.ndarray, F: np.ndarray,
                          groups: np.ndarray | None = None, sides: np.ndarray | None = None,
                          corners: np.ndarray | None = None) -> sp.csr_matrix:
    """The gather matrix G (k, m) with its rows averaged over the target's mesh where the
    binding jumps: U (k, 3) metres, the template's points (at rest) the target's vertices
    Y (k, 3), F (f, 3) are bound to, where the motion carried is the template's (measured on
    the fitted skin instead, the menpo3d mask folded 0.5 % for 0.4 %, the marble bust 0.28 %
    for 0.21 %, and its push_b_lip fell to 0.7x); an edge whose ends' U lie more than JUMP_STRETCH
    times its own length apart crosses a jump (a crease of the fitted skin, where
    neighbours on the target take closest points on either side of it, or the binding's
    fallback for a point facing away changes direction), and the motion carried there would
    shear the triangles across it and fold them. Within JUMP_RINGS rings of a jump (and
    OPENING_RINGS of an edge across an opening, below) the coordinates are replaced
    JUMP_ROUNDS times by the mean of their own and their covered neighbours'
    (_rows_averaged: coverage kept, split vertices (groups (k,)) one point).

    An edge across one of the template's openings jumps too, however short: sides (k,)
    (opening_sides) puts its ends on the two sides of one opening, and their template
    triangles (corners (k, 3): template vertex ids) share no vertex (at the opening's ends
    they do, and the motion is whole there). A target whose mouth or eyes are shut where the
    template's are open (a bust's carved lips) has vertices along the shut line bound to
    either lip by turns: as the lips part they pulled the line into a zigzag that folded
    (the marble bust's mouth line over expressions.fap: 29 triangles, 0.107 % of its face,
    now 20, 0.083 %; the smile's jagged mouth line is gone)."""
    from fae.mesh import adjacency_from_edges

    def step_of(edges, Yg, covered, first):
        k = len(Yg)
        length = np.linalg.norm(Yg[edges[:, 0]] - Yg[edges[:, 1]], axis=1)
        apart = np.linalg.norm(U[first][edges[:, 0]] - U[first][edges[:, 1]], axis=1)
        jump = apart > JUMP_STRETCH * np.maximum(length, 1e-9)
        if sides is not None and corners is not None:
            a, b = sides[first][edges[:, 0]], sides[first][edges[:, 1]]
            across = (a > 0) & (b > 0) & (a != b) & ((a + 1) // 2 == (b + 1) // 2)
            if across.any():
                ca, cb = corners[first][edges[across, 0]], corners[first][edges[across, 1]]
                across[across] = ~(ca[:, :, None] == cb[:, None, :]).any(axis=(1, 2))
        else:
            across = np.zeros(len(edges), dtype=bool)
        jump &= covered[edges].all(axis=1)
        across &= covered[edges].all(axis=1)
        zone = np.zeros(k, dtype=bool)
        zone[edges[jump].ravel()] = True
        if not zone.any() and not across.any():
            return None
        A = adjacency_from_edges(k, edges)
        for _ in range(JUMP_RINGS):
            zone |= (A @ zone.astype(np.float64)) > 0
        shut = np.zeros(k, dtype=bool)
        shut[edges[across].ravel()] = True
        for _ in range(OPENING_RINGS):
            shut |= (A @ shut.astype(np.float64)) > 0
        zone |= shut
        zone &= covered
        A = ((A + sp.identity(k, format="csr")) @ sp.diags(covered.astype(np.float64))).tocsr()  # covered neighbours
        mean = sp.diags(1.0 / np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1e-12)) @ A
        # the zone's rows are averaged; every other row stays itself
        return (sp.diags(zone.astype(np.float64)) @ mean + sp.diags((~zone).astype(np.float64))).tocsr()

    return _rows_averaged(G, Y, F, groups, JUMP_ROUNDS, step_of)


def _margin_rows(margin: np.ndarray, X: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The point of a lid margin (template vertex ids `margin`, at X (n, 3)) above or below
    each of x (j,) metres across the face: (j,) its height, (j, 2) template vertices and
    (j, 2) their weights (the two margin vertices either side, linearly; the end's beyond)."""
    order = margin[np.argsort(X[margin, 0], kind="stable")]
    mx, my = X[order, 0], X[order, 1]
    i = np.clip(np.searchsorted(mx, x), 1, len(order) - 1)
    a = np.clip((x - mx[i - 1]) / np.maximum(mx[i] - mx[i - 1], 1e-12), 0.0, 1.0)
    return (1.0 - a) * my[i - 1] + a * my[i], np.column_stack([order[i - 1], order[i]]), np.column_stack([1.0 - a, a])


def _eye_open(margins: list[np.ndarray], X: np.ndarray) -> float:
    """How far an eye opens: the most its upper and lower margins (template vertex ids, at
    X (n, 3)) lie apart over the lower margin's span, over that span's width."""
    x = X[margins[1], 0]
    return float(np.max(_margin_rows(margins[0], X, x)[0] - X[margins[1], 1]) / max(np.ptp(x), 1e-12))


def carved_eye_rows(template: FaceModel, X: np.ndarray, Y: np.ndarray, nearest: np.ndarray,
                    eyes: list[str]) -> tuple[np.ndarray, sp.csr_matrix]:
    """Target vertices over a carved eye, and the rows that bind them between its lids.

    A target whose eyeball is part of its skin (a bust's carved eye, a mask's painted one)
    binds the eyeball's surface to the lining of the template's lids, where it lies; as the
    upper lid closed, the part bound to its lining came down while the part bound to the
    lower lid's stayed, and the lid's front folded over it (the marble bust's blinks: 122
    triangles, dark wedges in the slit). Each such vertex, bound nearest to the hidden skin
    (`visible_skin`: the lining) of either lid of an eye in `eyes` (the eyes the target has
    no eyeball part for), or lying between the two margins of the fitted head X (n, 3),
    follows the two margins instead: the upper margin's motion above it times w and the
    lower margin's below it times 1 - w, w its height between the two in X (clipped to
    [0, 1]; across the lower margin's span). Closing, the upper margin comes down onto the
    lower one and draws the eye's surface in below it, every row of it in its order, as a
    curtain. An eye that X opens less than CARVED_EYE_OPEN of the template's (for its
    width) is shut already, and left as it is bound. Y (k, 3) the target's skin in the face
    frame (metres), nearest (k,) the template vertex each target vertex is bound nearest to.

    Returns (j,) target vertex ids and (j, n) rows over the template's vertices (each
    summing to one)."""
    from fae.adapt.transfer import visible_skin
    from fae.sim.build import LID_REGION_PAIRS, lid_margin_vertices

    names = list(template.region_names)
    region = np.asarray(template.skin_region)
    P = np.asarray(template.skin_vertices, dtype=np.float64)
    hidden = None
    ids, cols, weights = [], [], []
    for eye, lids in zip(("eye_l", "eye_r"), LID_REGION_PAIRS):
        if eye not in eyes or not all(r in names for r in lids):
            continue
        margins = [lid_margin_vertices(template, r, eye) for r in lids]
        if min(len(m) for m in margins) < 2:
            continue
        if _eye_open(margins, X) < CARVED_EYE_OPEN * _eye_open(margins, P):
            continue  # shut or nearly (a mask's slit): its lids are skin of their own, bound as they lie
        if hidden is None:
            hidden = ~visible_skin(template)
        on_lids = np.flatnonzero(np.isin(region[nearest], [names.index(r) for r in lids]))
        (y_up, c_up, w_up), (y_low, c_low, w_low) = (_margin_rows(m, X, Y[on_lids, 0]) for m in margins)
        x = Y[on_lids, 0]
        across = (x > X[margins[1], 0].min()) & (x < X[margins[1], 0].max())  # the lower margin's span
        between = across & (Y[on_lids, 1] > y_low) & (Y[on_lids, 1] < y_up)
        keep = between | (across & hidden[nearest[on_lids]])
        if not keep.any():
            continue
        over, y_up, c_up, w_up, y_low, c_low, w_low = (
            a[keep] for a in (on_lids, y_up, c_up, w_up, y_low, c_low, w_low))
        w = np.clip((Y[over, 1] - y_low) / np.maximum(y_up - y_low, 1e-9), 0.0, 1.0)
        ids.append(over)
        cols.append(np.hstack([c_up, c_low]))
        weights.append(np.hstack([w_up * w[:, None], w_low * (1.0 - w)[:, None]]))
    if not ids:
        return np.zeros(0, dtype=np.int64), sp.csr_matrix((0, len(X)))
    ids, cols, weights = np.concatenate(ids), np.vstack(cols), np.vstack(weights)
    rows = np.repeat(np.arange(len(ids)), cols.shape[1])
    return ids, sp.csr_matrix((weights.ravel(), (rows, cols.ravel())), shape=(len(ids), len(X)))


def template_resolution(face: np.ndarray, F: np.ndarray, X: np.ndarray, covered: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """How much finer than the template the target is, per target vertex bound to triangle
    face (k,) of the template's faces F (m, 3) on its fitted skin X (n, 3) metres (covered
    (k,) bool: the vertices that follow it): (density (k,): target vertices bound per template
    triangle, averaged over the triangles around each corner of its triangle; edge (k,)
    metres: the mean edge of its triangle on X). The template bound to itself has about
    0.4-1.3 (a vertex per two triangles); the menpo3d mask 3-27; the marble bust 0.3-2.7."""
    face = np.asarray(face, dtype=np.int64)
    F = np.asarray(F, dtype=np.int64)
    counts = np.bincount(face[np.asarray(covered, dtype=bool)], minlength=len(F)).astype(np.float64)
    around = sp.csr_matrix((np.ones(F.size), (F.ravel(), np.repeat(np.arange(len(F)), 3))), shape=(len(X), len(F)))
    per_corner = (around @ counts) / np.maximum(around @ np.ones(len(F)), 1.0)
    density = per_corner[F].mean(axis=1)
    edge = np.mean([np.linalg.norm(X[F[:, i]] - X[F[:, (i + 1) % 3]], axis=1) for i in range(3)], axis=0)
    return density[face], edge[face]


def smoothed_where_fine(G: sp.csr_matrix, Y: np.ndarray, F: np.ndarray, density: np.ndarray, edge: np.ndarray,
                        groups: np.ndarray | None = None, rounds: int = FINE_ROUNDS) -> sp.csr_matrix:
    """The gather matrix G (k, m) with each row averaged `rounds` times with its covered
    neighbours' over the target's mesh Y (k, 3) metres, F (f, 3), where the target is finer
    than the template: density (k,) and edge (k,) metres, from template_resolution. There
    (the menpo3d mask's 1 mm edges under the template's 3-4 mm) the motion a target is
    given is the template's piecewise-linear field, with a kink at every template edge, read
    through a binding that jitters from one target vertex to the next; its small triangles
    fold where the template's large ones only bend (a brow lowered, a cheek raised). A
    neighbour weighs exp(-(edge length / (FINE_SHARE x the template's local edge))^2) times
    how fine both ends are (0 at FINE_DENSITY[0] target vertices per template triangle, 1 from
    FINE_DENSITY[1]): averaged over a few of its own short edges, the field is smooth at the
    target's scale and all but unchanged at the template's (the FAPs' motion); a target as
    coarse as the template (about 0.5 per triangle) keeps its rows as they are. The reach is
    `rounds` of the target's edges: a target many times finer still than the mask is smoothed
    over less of the template's scale. Coverage kept, split vertices (groups (k,)) one point
    (_rows_averaged)."""
    lo, hi = FINE_DENSITY
    fine = np.clip((np.asarray(density, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0)
    reach = FINE_SHARE * np.asarray(edge, dtype=np.float64)

    def step_of(edges, Yg, covered, first):
        k = len(Yg)
        e = edges[covered[edges].all(axis=1)]
        f, r = fine[first], reach[first]
        length = np.linalg.norm(Yg[e[:, 0]] - Yg[e[:, 1]], axis=1)
        w = np.minimum(f[e[:, 0]], f[e[:, 1]]) * np.exp(-(length / np.maximum(r[e].mean(axis=1), 1e-12)) ** 2)
        e, w = e[w > FINE_LEAST], w[w > FINE_LEAST]
        if len(e) == 0:
            return None
        W = sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(k, k))
        W = (W + sp.identity(k)).tocsr()
        return (sp.diags(1.0 / np.asarray(W.sum(axis=1)).ravel()) @ W).tocsr()

    return _rows_averaged(G, Y, F, groups, rounds, step_of)


def facing_against(Y: np.ndarray, F: np.ndarray, X: np.ndarray, XF: np.ndarray, reach: float = COVERAGE_FAR) -> float:
    """Share (0..1) of the target's vertices Y (k, 3) metres, faces F (f, 3), within `reach`
    metres of the fitted skin X (n, 3), XF (m, 3), whose normal points against the skin's
    there: a mesh wound inside out has nearly all of them (its normals point into the head,
    and no vertex binds), one with faces wound against their neighbours or doubled back to
    back a sixth to a half; a good mesh's creases and folds a few per cent (the menpo3d mask
    2 %, the marble bust 3 %)."""
    from fae.adapt.query import MeshQuery

    _, dist, face, bary = MeshQuery(X, XF).closest_points(Y)
    near = np.isfinite(dist) & (dist < reach) & (face >= 0)
    if not near.any():
        return 0.0
    NX = vertex_normals(X, XF)
    skin = np.einsum("kj,kjd->kd", bary[near], NX[XF[face[near]]])
    own = vertex_normals(Y, F)[near]
    return float(np.mean(np.einsum("ij,ij->i", skin, own) < 0.0))


def part_colors(target: TargetMesh, index: np.ndarray, V: np.ndarray, template_part: Part) -> np.ndarray | None:
    """(k, 4) float32 linear RGBA vertex colours of a rigid part of the target: its vertices
    `index` (k,), at V (k, 3) in the face frame, sit on the fitted head's `template_part`.
    Sampled from the target's own texture where it has one (an eyeball's iris is painted
    on it), else the nearest vertex's colour of the template's part (its iris and pupil;
    an eyeball drawn in one colour stared white); None when neither has colours."""
    if target.texture is not None and target.uv is not None:
        from fae.adapt.texture import bilinear_samples

        H, W = target.texture.shape[:2]
        u = np.mod(target.uv[index, 0], 1.0)  # u wraps and v stops at the edges, as the renderer draws them
        v = np.clip(target.uv[index, 1], 0.0, 1.0)
        srgb = bilinear_samples(target.texture, u * W, (1.0 - v) * H) / 255.0
        return np.column_stack([srgb ** 2.2, np.ones(len(index))]).astype(np.float32)  # the renderer's gamma
    if template_part.vertex_colors is None:
        return None
    from scipy.spatial import cKDTree

    return np.asarray(template_part.vertex_colors, np.float32)[cKDTree(template_part.vertices).query(V)[1]]


def _part(target: TargetMesh, index: np.ndarray, V: np.ndarray, F: np.ndarray, template_part: Part, bone: str) -> Part:
    """A rigid part of the target (its vertices `index`, at V in the face frame, faces F)
    sitting on the fitted head's `template_part`, coloured by part_colors. Its base colour
    is its most common one where the colours are the target's own (the renderer tells an
    eye's iris from its white by that colour: the template's white took a painted sclera
    for iris, and a pupil's dilation stretched the whole eyeball)."""
    colors = part_colors(target, index, V, template_part)
    own = target.texture is not None and target.uv is not None and colors is not None
    color = np.median(colors, axis=0) if own else np.asarray(template_part.color, np.float32)
    return Part(vertices=V, faces=F.astype(np.int32), color=np.asarray(color, np.float32), bone=bone,
                vertex_colors=colors)


def skin_pieces(V: np.ndarray, F: np.ndarray, label: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(c,) bool over the connected pieces `label` (n,) of mesh V (n, 3), F (m, 3): the skin
    to fit. The face is the piece that most of the feature points `points` (k, 3) lie
    closest to; any piece at least PART_SIZE_SHARE of its size (bounding-box diagonal) is
    skin too (a scalp or neck meshed apart); the smaller ones are eyes, teeth, or bits
    (judged later). Vertex counts say nothing: an artist's eyeballs may be meshed finer than
    the head."""
    from fae.adapt.query import MeshQuery

    count = int(label.max()) + 1
    face = MeshQuery(V, F).closest_points(points)[2]
    face_piece = int(np.argmax(np.bincount(label[F[face[face >= 0], 0]], minlength=count)))
    lo = np.full((count, 3), np.inf)
    hi = np.full((count, 3), -np.inf)
    np.minimum.at(lo, label, V)
    np.maximum.at(hi, label, V)
    size = np.linalg.norm(hi - lo, axis=1)
    return size >= PART_SIZE_SHARE * size[face_piece]


def retarget(template: FaceModel, target: TargetMesh, say: Callable[[str], None] | None = None) -> Retarget:
    """Bind `target` to `template` (module docstring). Raises RetargetError when the target
    cannot be animated (too few feature points, no head found at them)."""
    from fae.adapt.calibration import apply_transform
    from fae.adapt.query import MeshQuery
    from fae.adapt.workflow import AdaptRefused, FacePairsUnavailable, adapt_scan
    from fae.mpeg4.faptables import fapu_of
    from fae.mpeg4.fapu import fapu0_from_positions, fapu_from_fapu0

    say = say or (lambda msg: None)
    names = usable_landmarks(template, target.landmarks)
    if len(names) < MIN_FEATURE_POINTS:
        raise RetargetError(
            f"{target.landmarks_path}: {len(names)} usable feature points on the template's skin "
            f"({', '.join(sorted(names)) or 'none'}); at least {MIN_FEATURE_POINTS} expected (MPEG-4 names such "
            "as 3.7, 3.11, 8.3, 8.4, 9.3, 2.1, or 68 iBUG points)")
    V = np.asarray(target.vertices, dtype=np.float64)
    F = np.asarray(target.faces, dtype=np.int64)
    n = len(V)
    label = welded_components(V, F)
    candidate = ~skin_pieces(V, F, label, np.array([target.landmarks[k] for k in names]))[label]

    def no_pairs(part_V, part_F):
        raise FacePairsUnavailable("the feature points given stand in for a face-landmark model", fatal=False)

    fit_index, fit_F = _sub_mesh(F, ~candidate)
    for turned in (False, True):
        try:
            fitted, fit_report, _ = adapt_scan(template, V[fit_index], fit_F, no_pairs,
                                               {k: target.landmarks[k] for k in names}, scan_name=target.path,
                                               landmarks_name=target.landmarks_path, say=say, landmark_mesh=(V, F))
        except AdaptRefused as exc:
            raise RetargetError(str(exc)) from None
        # the fit pairs the scan's points by their normals: a mesh wound inside out is fitted again, turned
        against = facing_against(apply_transform(np.linalg.inv(fitted.scan_transform), V[fit_index]), fit_F,
                                 np.asarray(fitted.skin_vertices, dtype=np.float64),
                                 np.asarray(template.skin_faces, dtype=np.int64))
        if turned or against <= INSIDE_OUT_SHARE:
            break
        say(f"{target.path}: its faces are wound inside out ({against * 100:.0f} % face into the head); "
            "turned outward")
        # the skin's faces only: the small pieces (eyes, teeth) keep the winding they were given
        skin_faces = ~candidate[F[:, 0]]
        F = np.ascontiguousarray(np.where(skin_faces[:, None], F[:, ::-1], F))
        fit_F = np.ascontiguousarray(fit_F[:, ::-1])
    if against > MIXED_WINDING_SHARE:
        raise RetargetError(
            f"{target.path}: {against * 100:.0f} % of its surface faces into the head (faces wound against their "
            f"neighbours, or doubled back to back); expected one outward winding (at most "
            f"{MIXED_WINDING_SHARE * 100:.0f} %; a mesh tool's 're-orient faces coherently' mends it)")
    for line in fit_report.get("verdict", []):
        say(f"warning: the template's fit to {target.path}: {line}")
    kept = list(fit_report.get("landmarks_used", names))
    if len(kept) < MIN_FEATURE_POINTS:  # the fit set aside points that disagree with the others or lie off the mesh
        raise RetargetError(
            f"{target.landmarks_path}: {len(kept)} feature points are usable "
            f"({', '.join(sorted(set(names) - set(kept)))} set aside: they disagree with the others or lie off the "
            f"mesh, as said above); at least {MIN_FEATURE_POINTS} expected")
    T = np.linalg.inv(fitted.scan_transform)
    Y = apply_transform(T, V)

    # the small pieces: rigid parts where they sit on the fitted head's eyes, teeth, tongue
    parts_at: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}  # target part -> (template part, V, F)
    part_index: dict[str, np.ndarray] = {}
    part_bone: dict[str, str] = {}
    queries = {p: MeshQuery(*fitted.mesh(p)) for p in RIGID_PARTS if p in fitted.parts}
    on_faces = np.bincount(F.ravel(), minlength=n) > 0
    # (vertices no triangle uses, which a PLY keeps, are pieces of their own with nothing to draw)
    for c in np.unique(label[candidate & on_faces]):
        members = label == c
        Yc = Y[members]
        size = float(np.linalg.norm(np.ptp(Yc, axis=0)))
        best, best_d = None, np.inf
        for p, q in queries.items():
            d = float(np.median(q.closest_points(Yc)[1]))
            if d < best_d:
                best, best_d = p, d
        if best is None or best_d > max(PART_REACH * size, PART_REACH_MIN):
            candidate[members] = False  # skin after all (a stray sliver, a separate ear...)
            continue
        name = best if best not in part_index else f"{best}_{sum(k.startswith(best) for k in part_index)}"
        idx, pf = _sub_mesh(F, members)
        part_index[name] = idx
        part_bone[name] = fitted.parts[best].bone
        parts_at[name] = (best, Y[idx], pf)
    skin_index, skin_F = _sub_mesh(F, ~candidate)
    loose = np.flatnonzero(~on_faces)
    if len(skin_F) == 0:
        raise RetargetError(f"{target.path}: no skin triangles left after the rigid parts (eyes, teeth) were found")
    Ys = Y[skin_index]

    # the binding: closest point of the fitted skin, and how fully each vertex follows
    P = np.asarray(template.skin_vertices, dtype=np.float64)
    X = np.asarray(fitted.skin_vertices, dtype=np.float64)
    TF = np.asarray(template.skin_faces, dtype=np.int64)
    given = {k: apply_transform(T, np.asarray(target.landmarks[k], dtype=np.float64)[None])[0]
             for k in fit_report.get("landmarks_used", names)}
    pins = [k for k in given if template.feature_points[k].part == "skin"]
    X = pinned_to_points(X, TF, np.array([fitted.feature_points[k].triangle for k in pins]),
                         np.array([fitted.feature_points[k].bary for k in pins]), np.array([given[k] for k in pins]),
                         PIN_REACH)
    # normals shared across the mesh's texture seams: both copies of a split vertex bind to
    # the same point, or the seam opens into a crack as soon as the face moves
    seams = seam_groups(Ys, skin_F)
    NY = vertex_normals(Ys, skin_F, corner_index=seams[skin_F].ravel())[seams]
    face, bary, dist = bind_to_surface(Ys, X, TF, NY)
    coverage = coverage_weights(dist, COVERAGE_NEAR, COVERAGE_FAR)
    bound = np.zeros(len(P), dtype=bool)
    bound[TF[face[coverage > 0.5]].ravel()] = True
    Tv, scale = frame_transforms(P, X, TF, used=bound)
    G = gather_matrix(face, bary, coverage, TF, len(P))
    U = np.einsum("kj,kjd->kd", bary, P[TF[face]])  # the template's points they are bound to, at rest
    nearest = TF[face, np.argmax(bary, axis=1)]
    skin_region = np.asarray(template.skin_region, dtype=np.int32)[nearest]
    G = smoothed_across_jumps(G, U, Ys, skin_F, seams, opening_sides(template.region_names, skin_region), TF[face])
    G = smoothed_where_fine(G, Ys, skin_F, *template_resolution(face, TF, X, coverage > 0.5), groups=seams)
    # eyes carved into the skin (no eyeball part): their rows between the lids (carved_eye_rows)
    curtains = {e: carved_eye_rows(template, X, Ys, nearest, [e]) for e in ("eye_l", "eye_r")
                if all(src != e for src, _, _ in parts_at.values())}
    curtains = {e: c for e, c in curtains.items() if len(c[0])}

    # the target as a FaceModel
    feature_points, fp_source = _target_feature_points(template, fitted, given, Ys, U, skin_F, skin_region, parts_at)
    if target.uv is None:
        uv, texture = np.zeros((len(skin_index), 2), np.float32), None
    else:  # a FaceModel's v runs down the image from its first row (glTF's way)
        uv = np.column_stack([target.uv[skin_index, 0], 1.0 - target.uv[skin_index, 1]]).astype(np.float32)
        texture = target.texture
    model = FaceModel(
        skin_vertices=Ys, skin_faces=skin_F.astype(np.int32), skin_uv=uv, skin_texture=texture,
        skin_color=np.asarray(template.skin_color, np.float32), skin_mirror=np.arange(len(Ys), dtype=np.int32),
        skin_region=skin_region, region_names=list(template.region_names), skin_thickness=np.zeros(len(Ys)),
        layer_params={},
        parts={k: _part(target, part_index[k], v, f, fitted.parts[src], part_bone[k])
               for k, (src, v, f) in parts_at.items()},
        jaw_pivot=np.asarray(fitted.jaw_pivot, np.float64), jaw_axis=np.asarray(fitted.jaw_axis, np.float64),
        eye_centers={k: np.asarray(v, np.float64) for k, v in fitted.eye_centers.items()},
        feature_points=feature_points, muscles=[], scan_transform=np.asarray(fitted.scan_transform),
        meta={"name": Path(target.path).stem, "generator": "fae motion transfer", "source": Path(target.path).name})

    template_fapu = fapu_of(template)
    try:
        target_fapu = fapu_of(model)
    except (KeyError, ValueError):  # a target without eyes' or mouth's points: the fitted head's
        target_fapu = fapu_from_fapu0(fapu0_from_positions(fitted.feature_point_positions()))
    ratio = _fapu_ratio(template_fapu, target_fapu)
    rest_fp = template.feature_point_positions()
    fitted_fp = fitted.feature_point_positions()
    anchors = {"head": (rest_fp["7.1"], fitted_fp["7.1"]) if "7.1" in rest_fp else
               (np.asarray(template.jaw_pivot), np.asarray(fitted.jaw_pivot)),
               "jaw": (np.asarray(template.jaw_pivot), np.asarray(fitted.jaw_pivot))}
    anchors["tongue"] = anchors["jaw"]
    for eye in ("eye_l", "eye_r"):
        if eye in template.eye_centers and eye in fitted.eye_centers:
            anchors[eye] = (np.asarray(template.eye_centers[eye]), np.asarray(fitted.eye_centers[eye]))
        else:
            anchors[eye] = anchors["head"]
    face_regions = [template.region_names.index(r) for r in ("forehead", "nose", "cheek_l", "cheek_r", "lip_upper",
                                                              "lip_lower", "chin") if r in template.region_names]
    in_face = np.isin(skin_region, face_regions) & (coverage > 0.5)
    local_scale = float(np.median(scale[nearest[in_face]][:, [0, 2]])) if in_face.any() else float("nan")
    report = {
        "target": target.path, "vertices": n, "skin_vertices": int(len(skin_index)),
        "parts": {k: {"template_part": parts_at[k][0], "vertices": int(len(v))} for k, v in part_index.items()},
        "landmarks_used": list(fit_report.get("landmarks_used", names)),
        "turned_outward": bool(turned),  # its skin was wound inside out, and was fitted again turned
        "fit": {"errors": fit_report.get("errors"), "folded_triangles": fit_report.get("folded_triangles"),
                "verdict": fit_report.get("verdict", []), "seconds": fit_report.get("seconds")},
        "coverage": {"full": int((coverage >= 1.0).sum()), "partial": int(((coverage > 0) & (coverage < 1)).sum()),
                     "none": int((coverage <= 0).sum())},
        "fapu_template": template_fapu, "fapu_target": target_fapu, "fapu_ratio": ratio,
        "local_scale_median_face": local_scale,
        "feature_points": fp_source,
    }
    chin = fitted_fp["2.1"][1] if "2.1" in fitted_fp else float(Ys[:, 1].min())
    neck = coverage_weights(chin - Ys[:, 1], *NECK_FADE)
    # what the template does not reach above the chin (a hat, hair standing off the scalp, a
    # wreath's leaves) turns with the head as one body: held by its coverage alone, it stayed
    # put while the head turned under it. Only on pieces that touch the head (within
    # PIECE_REACH of the fitted skin): a second head or a prop beside it swung with this one
    piece = label[skin_index]
    piece_reach = np.full(int(label.max()) + 1, np.inf)  # metres from each piece to the fitted skin
    np.minimum.at(piece_reach, piece, dist)
    above = coverage_weights(chin - Ys[:, 1], *ABOVE_CHIN) * (piece_reach[piece] <= PIECE_REACH)
    if "2.1" not in fitted_fp:  # no chin to stand above: the coverage alone
        above[:] = 0.0
    head = _playable_template(template)
    fap_motion = _template_fap_motion(template, np.arange(len(P)), head)

    def retarget_with(eyes: tuple[str, ...]) -> Retarget:
        # the Retarget with the rows of the carved eyes `eyes` between their lids
        Ge = G
        if eyes:
            over = np.concatenate([curtains[e][0] for e in eyes])
            rows = sp.vstack([curtains[e][1] for e in eyes]).tocsr()
            keep = np.ones(len(Ys))
            keep[over] = 0.0
            placed = sp.csr_matrix((coverage[over], (over, np.arange(len(over)))), shape=(len(Ys), len(over)))
            Ge = (sp.diags(keep) @ G + placed @ rows).tocsr()
        used = np.flatnonzero(np.asarray(abs(Ge).sum(axis=0)).ravel() > 0)
        rt = Retarget(model=model, skin_index=skin_index, head_weight=np.maximum(coverage, above) * neck,
                      part_index=part_index, used=used,
                      frame_transform=np.ascontiguousarray(Tv[used]), gather=Ge[:, used].tocsr(), coverage=coverage,
                      anchors=anchors, scale=ratio, report=dict(report), vertex_count=n, normal_groups=seams,
                      loose=(loose, Y[loose]))
        rt.fapu_gain, rt.report["fapu_gains"] = fapu_gain_field(
            model, lambda motion: rt.displacements(np.broadcast_to(motion, (len(used), 3))), template_fapu,
            target_fapu, fap_motion={k: (m[used], own) for k, (m, own) in fap_motion.items()})
        return rt

    rt = retarget_with(())
    if curtains:
        # a carved eye closes between its lids where that keeps more of it whole at the
        # template's own blink (a coarse bust's few big triangles over the eye fold less
        # bound as they lie: Demosthenes'); a template without its mapping cannot blink here
        # (calibrating it would take tens of seconds): its carved eyes stay as they are bound
        eyes: tuple[str, ...] = ()
        if head is not None:
            blink = _template_blink(template, head)
            both = retarget_with(tuple(curtains))
            eyes = tuple(e for e in curtains if _eye_folds(both, blink, e) < _eye_folds(rt, blink, e))
            rt = both if eyes == tuple(curtains) else retarget_with(eyes) if eyes else rt
        rt.report["carved_eyes"] = {e: ("closed between the lids" if e in eyes else "bound as it lies")
                                    for e in curtains}
    return rt


def _template_blink(template: FaceModel, head) -> np.ndarray:
    """(n, 3) metres: the template skin's motion with both upper lids closed to their limit,
    settled (head: its PlayableHead)."""
    from fae.mpeg4.faptables import FAP_LIMITS
    from fae.animate.player import Player
    from fae.animate.verify import settled_skin

    values = np.zeros(68)
    values[[18, 19]] = FAP_LIMITS[[18, 19], 1]  # close_t_l_eyelid, close_t_r_eyelid
    return settled_skin(Player(head), values, max_frames=SETTLE_FRAMES) - \
        np.asarray(template.skin_vertices, dtype=np.float64)


def _eye_folds(rt: Retarget, motion: np.ndarray, eye: str) -> int:
    """Triangles of the lids of `eye` (the target's regions) that the template's motion
    (n, 3) folds on the target bound as `rt`."""
    from fae.adapt.nonrigid import folded_triangles
    from fae.sim.build import LID_REGION_PAIRS

    m = rt.model
    names = list(m.region_names)
    lids = LID_REGION_PAIRS[("eye_l", "eye_r").index(eye)]
    F = np.asarray(m.skin_faces, dtype=np.int64)
    on = np.isin(np.asarray(m.skin_region)[F], [names.index(r) for r in lids if r in names]).any(axis=1)
    V = np.asarray(m.skin_vertices, dtype=np.float64)
    return int((folded_triangles(V, V + rt.displacements(motion[rt.used]), F) & on).sum())


class RetargetPlayer:
    """Plays FAP frames on a target through a Player of the template (module docstring).

    face         the target's FaceModel (Retarget.model): what verify_faps and the renderer read
    step(frame, dt=None) -> (k, 3) the target's skin, face frame, metres
    play(stream, fps=None) -> PlayedFrame per frame (skin and bone poses of the target)
    reset()
    lead_off()   the template player's (Player.lead_off): a context for settled poses
    """

    def __init__(self, rt: Retarget, player):
        self.retarget = rt
        self.player = player
        self.face = rt.model
        self.fps = player.fps
        self._rest = np.asarray(rt.model.skin_vertices, dtype=np.float64)
        self.reset()

    def reset(self) -> None:
        """Back to the neutral face; the template's neutral skin (the motion's zero) is taken
        from the template player itself, so a neutral frame leaves the target at rest exactly."""
        from fae.mpeg4.faps import FAP_COUNT

        p = self.player
        p.reset()
        self._neutral = np.asarray(p.step(np.zeros(FAP_COUNT), dt=1.0 / self.fps), dtype=np.float64)[self.retarget.used]
        p.reset()
        self.bone_transforms = {b: np.eye(4) for b in BONES}
        self.pupil_scale = dict(p.pupil_scale)
        self.values = p.values

    def lead_off(self):
        """Steps inside go without the template player's lids' lead (Player.lead_off)."""
        return self.player.lead_off()

    def step(self, frame, dt: float | None = None) -> np.ndarray:
        """Advance the template one frame (see Player.step) and return the target's skin (k, 3)."""
        skin = self.player.step(frame, dt=dt)
        out, self.bone_transforms = self.carry(skin, self.player.bone_transforms)
        self.pupil_scale = dict(self.player.pupil_scale)
        self.values = self.player.values
        return out

    def carry(self, skin: np.ndarray, bones: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The transfer alone: the template's skin (V, 3) and bone poses of one frame -> the
        target's skin (k, 3) and bone poses (face frame, metres)."""
        rt = self.retarget
        H = bones["head"]
        moved = skin[rt.used]
        still = np.array_equal(H, np.eye(4))
        if not still:  # the head pose off: motion in the head's own frame
            moved = (moved - H[:3, 3]) @ H[:3, :3]
        out = self._rest + rt.displacements(moved - self._neutral)
        target_bones = {"head": H if still else rt.bone_pose("head", H)}
        for bone, M in bones.items():
            if bone != "head":
                target_bones[bone] = rt.bone_pose(bone, M, H)
        if not still:
            Ht = target_bones["head"]
            out += rt.head_weight[:, None] * ((out @ Ht[:3, :3].T + Ht[:3, 3]) - out)
        return out, target_bones

    def play(self, stream, fps: float | None = None) -> Iterator:
        """Play a FapStream (resampled to `fps`, None: its own) or an iterable of DenseFrames;
        yields fae.animate.player.PlayedFrame of the target."""
        from fae.animate.player import PlayedFrame, stream_frames

        frames, rate = stream_frames(stream, fps, self.fps)
        if rate != self.fps:
            self.fps = rate
            self.player.fps = rate
            self.reset()
        for i, frame in enumerate(frames):
            skin = self.step(frame, dt=1.0 / rate)
            yield PlayedFrame(index=int(getattr(frame, "index", i)), time=float(getattr(frame, "time", i / rate)),
                              skin_vertices=skin, bone_transforms={k: v.copy() for k, v in self.bone_transforms.items()},
                              pupil_scale=dict(self.pupil_scale), values=np.array(self.values, copy=True))
