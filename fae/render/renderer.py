"""Headless frames of a FaceModel: the only module in fae that imports pyrender or OpenGL.

`FaceRenderer(model, size, view, supersample).render(skin_vertices, bone_transforms)`
returns an (H, W, 3) uint8 RGB image. Everything the frame loop needs (scene, GL buffers,
shader programs, index arrays) is made once in the constructor. Skin, its dark inward copy
(the mouth cavity) and the rigid parts are one primitive with vertex colours: a frame
poses the parts on the CPU, writes positions and normals into the existing vertex buffer
(`glBufferSubData`, no GL objects created per frame), draws once and reads the colour
buffer back (no depth readback).

pyrender 0.1.45 under OSMesa and numpy 2 needs three fixes, applied once on import by
`_patch_pyrender()` and documented there: its `Mesh.bounds` uses `np.infty` (gone in
numpy 2); its shader-program cache is keyed on a ctypes context pointer that OSMesa
returns as a new object on every call, so the cache never hits (every frame recompiles
the shaders and leaks about 3 MB); an integer background colour renders black (we always
pass floats).
"""

from __future__ import annotations

import ctypes
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402
import OpenGL.contextdata  # noqa: E402
import pyrender  # noqa: E402
from OpenGL import GL  # noqa: E402
from pyrender.shader_program import ShaderProgramCache  # noqa: E402

from fae.io.facemodel import FaceModel  # noqa: E402
from fae.render.framing import VIEWS, CameraView, camera_view  # noqa: E402
from fae.render.normals import per_vertex_normals  # noqa: E402

# Linear RGB colours and materials. The background is applied as-is (no gamma).
BACKGROUND = (0.80, 0.82, 0.85)
CAVITY_COLOR = (0.045, 0.010, 0.012, 1.0)  # inside of the mouth and head, seen through openings
AMBIENT = 0.22
# Parts that are anatomy inside the head: drawn in the cavity colour so that the mouth
# opening shows a dark interior instead of bone.
INTERIOR_PARTS = ("cranium", "mandible")
_ROUGHNESS = {"skin": 0.6}

# Light rig in camera coordinates (x right, y up, +z towards the viewer): direction the
# light comes FROM and intensity. A warm key from the upper left, a cool softer fill from
# the right, a rim light from behind and above to separate the head from the background.
_LIGHTS = (
    ((-0.55, 0.55, 1.0), (1.0, 0.97, 0.92), 3.2),
    ((0.85, 0.05, 0.8), (0.88, 0.92, 1.0), 1.3),
    ((0.2, 0.9, -0.9), (1.0, 1.0, 1.0), 1.6),
)

_patched = False


def _current_context_address() -> int:
    """Integer address of the current GL context (stable across calls, unlike the pointer object)."""
    ctx = OpenGL.contextdata.getContext()
    address = ctypes.cast(ctx, ctypes.c_void_p).value if not isinstance(ctx, int) else ctx
    return int(address or 0)


def _patch_pyrender() -> None:
    """Fix pyrender 0.1.45 for numpy 2 and OSMesa; idempotent.

    1. `Mesh.bounds` starts from `np.infty`, removed in numpy 2: replaced by a property
       that takes the min/max over the primitives' bounds.
    2. `ShaderProgramCache.get_program` keys its cache on `OpenGL.contextdata.getContext()`;
       under OSMesa each call returns a new pointer object that compares unequal, so every
       frame compiled the shaders again and leaked about 3 MB. Wrapped so that programs are
       looked up by the context's integer address first; the original method runs only on
       a miss (once per shader variant). `clear()` empties both caches.
    """
    global _patched
    if _patched:
        return

    def mesh_bounds(self):
        if self._bounds is None:
            lows = np.array([p.bounds[0] for p in self.primitives])
            highs = np.array([p.bounds[1] for p in self.primitives])
            self._bounds = np.array([lows.min(axis=0), highs.max(axis=0)])
        return self._bounds

    if not hasattr(np, "infty"):
        pyrender.Mesh.bounds = property(mesh_bounds, doc="(2, 3) float: axis-aligned bounds of the mesh.")

    original_get_program = ShaderProgramCache.get_program
    original_clear = ShaderProgramCache.clear

    def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
        key = (_current_context_address(), vertex_shader, fragment_shader, geometry_shader,
               tuple(sorted((defines or {}).items())))
        programs = self.__dict__.setdefault("_programs_by_address", {})
        program = programs.get(key)
        if program is None:
            program = original_get_program(self, vertex_shader, fragment_shader, geometry_shader, defines)
            programs[key] = program
        return program

    def clear(self):
        original_clear(self)
        self.__dict__.pop("_programs_by_address", None)

    get_program.__doc__ = original_get_program.__doc__
    ShaderProgramCache.unpatched_get_program = original_get_program  # kept for tools/bench_play.py's baseline
    ShaderProgramCache.get_program = get_program
    ShaderProgramCache.clear = clear
    _patched = True


_patch_pyrender()


def _make_platform(width: int, height: int):
    name = os.environ.get("PYOPENGL_PLATFORM", "osmesa")
    if name == "osmesa":
        from pyrender.platforms.osmesa import OSMesaPlatform

        platform = OSMesaPlatform(width, height)
    elif name == "egl":
        from pyrender.platforms.egl import EGLPlatform, get_device_by_index

        platform = EGLPlatform(width, height, device=get_device_by_index(int(os.environ.get("EGL_DEVICE_ID", "0"))))
    else:
        raise RuntimeError(f"PYOPENGL_PLATFORM={name!r}: fae renders headless with 'osmesa' (or 'egl')")
    platform.init_context()
    platform.make_current()
    return platform


def _material(color, roughness: float) -> pyrender.MetallicRoughnessMaterial:
    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=np.asarray(color, dtype=np.float64).reshape(4),
        metallicFactor=0.0,
        roughnessFactor=float(roughness),
        doubleSided=False,
    )


class FaceRenderer:
    """Renders one FaceModel, frame after frame, into RGB images.

    model        the head (skin + rigid parts); never modified
    size         (width, height) of the output image, pixels
    view         "front", "three-quarter" or "profile" (camera framed from the head's
                 feature points, see fae.render.framing)
    supersample  k >= 1: render at k x size and average k x k blocks (anti-aliasing; OSMesa
                 has no multisampling). Costs about k^2 in fragment work.
    background   linear RGB floats in [0, 1]

    Use as a context manager or call `close()` to free the GL context.
    """

    def __init__(self, model: FaceModel, size: tuple[int, int] = (640, 480), view: str = "front",
                 supersample: int = 1, background=BACKGROUND):
        width, height = (int(s) for s in size)
        if width <= 0 or height <= 0:
            raise ValueError(f"image size {width}x{height}: expected positive width and height")
        if int(supersample) != supersample or supersample < 1:
            raise ValueError(f"supersample {supersample!r}: expected an integer >= 1")
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}: expected one of {', '.join(VIEWS)}")
        self.model = model
        self.size = (width, height)
        self.supersample = int(supersample)
        self.view = view
        self._vw, self._vh = width * self.supersample, height * self.supersample
        self.camera: CameraView = camera_view(model, view, aspect=width / height)

        bg = np.asarray(background, dtype=np.float64).reshape(-1)[:3]
        self._scene = pyrender.Scene(bg_color=np.append(bg, 1.0), ambient_light=np.full(3, AMBIENT))
        cam = pyrender.PerspectiveCamera(yfov=self.camera.yfov, znear=self.camera.znear,
                                         zfar=self.camera.zfar, aspectRatio=width / height)
        self._scene.add(cam, pose=self.camera.pose)
        self._add_lights()

        # Everything is one primitive (one draw call, one buffer upload per frame; pyrender
        # spends about 1 ms of Python per primitive per frame): the skin, a dark copy of it
        # facing inwards (reversed triangles; it shows only through openings such as the
        # mouth or the back of a face-only mesh), then every rigid part, posed on the CPU.
        # Colours are per vertex, so the material is white.
        rest = np.asarray(model.skin_vertices, dtype=np.float64)
        faces = np.asarray(model.skin_faces, dtype=np.int64)
        if rest.ndim != 2 or rest.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"skin: expected vertices (V, 3) and faces (F, 3), got {rest.shape} and {faces.shape}")
        nv = rest.shape[0]
        self._skin_rest = rest
        self._skin_faces = faces
        self._corner_index = faces.ravel()
        self._skin_rest_normals = per_vertex_normals(rest, faces, self._corner_index)
        skin_color = np.asarray(model.skin_color, dtype=np.float32).reshape(4)
        positions = [rest, rest]
        normals = [self._skin_rest_normals, -self._skin_rest_normals]
        colors = [np.tile(skin_color, (nv, 1)), np.tile(np.asarray(CAVITY_COLOR, dtype=np.float32), (nv, 1))]
        tris = [faces, faces[:, ::-1] + nv]
        offset = 2 * nv
        self._parts = []  # (bone, slice into the vertex arrays, rest vertices, rest normals)
        for name, part in model.parts.items():
            pv = np.asarray(part.vertices, dtype=np.float64)
            pf = np.asarray(part.faces, dtype=np.int64)
            if pv.size == 0 or pf.size == 0:
                continue
            pn = per_vertex_normals(pv, pf)
            if name in INTERIOR_PARTS:
                pc = np.tile(np.asarray(CAVITY_COLOR, dtype=np.float32), (len(pv), 1))
            elif part.vertex_colors is not None:
                pc = np.asarray(part.vertex_colors, dtype=np.float32).reshape(-1, 4)
            else:
                pc = np.tile(np.asarray(part.color, dtype=np.float32).reshape(4), (len(pv), 1))
            positions.append(pv)
            normals.append(pn)
            colors.append(pc)
            tris.append(pf + offset)
            self._parts.append((part.bone, slice(offset, offset + len(pv)), pv, pn))
            offset += len(pv)
        colors = np.concatenate(colors).astype(np.float32)
        colors[:, 3] = 1.0  # opaque: pyrender would otherwise sort and blend
        self._vertex_count = offset
        self._primitive = pyrender.Primitive(
            positions=np.concatenate(positions), normals=np.concatenate(normals), color_0=colors,
            indices=np.concatenate(tris), material=_material((1.0, 1.0, 1.0, 1.0), _ROUGHNESS["skin"]))
        self._scene.add(pyrender.Mesh([self._primitive]), name="head")
        # Interleaved float32 staging array in the primitive's buffer layout (position,
        # normal, colour); positions and normals are rewritten in place every frame.
        self._staging = np.empty((offset, 10), dtype=np.float32)
        self._staging[:, 6:] = colors

        self._platform = _make_platform(self._vw, self._vh)
        self._renderer = pyrender.Renderer(self._vw, self._vh)
        self._flags = pyrender.RenderFlags.NONE  # draws into the default framebuffer; no depth readback
        self._renderer.render(self._scene, self._flags)  # creates the GL buffers and shader programs once
        self._closed = False

    def _add_lights(self) -> None:
        R = self.camera.pose[:3, :3]
        for from_dir, color, intensity in _LIGHTS:
            towards_light = R @ (np.asarray(from_dir) / np.linalg.norm(from_dir))
            pose = np.eye(4)
            # A directional light shines along its node's -z: point +z towards the light.
            z = towards_light
            x = np.cross((0.0, 1.0, 0.0), z)
            if np.linalg.norm(x) < 1e-6:
                x = np.array([1.0, 0.0, 0.0])
            x /= np.linalg.norm(x)
            pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, np.cross(z, x), z
            self._scene.add(pyrender.DirectionalLight(color=np.asarray(color), intensity=intensity), pose=pose)

    def frame_geometry(self, skin_vertices=None, bone_transforms=None) -> tuple[np.ndarray, np.ndarray]:
        """(positions, normals), each (n, 3) float64, of everything drawn in one frame: skin,
        its inward copy, then the rigid parts posed by their bones (see `render`)."""
        if skin_vertices is None:
            V, N = self._skin_rest, self._skin_rest_normals
        else:
            V = np.asarray(skin_vertices, dtype=np.float64)
            if V.shape != self._skin_rest.shape:
                raise ValueError(f"skin_vertices: expected shape {self._skin_rest.shape}, got {V.shape}")
            N = per_vertex_normals(V, self._skin_faces, self._corner_index)
        P = np.empty((self._vertex_count, 3))
        Q = np.empty((self._vertex_count, 3))
        nv = V.shape[0]
        P[:nv], P[nv:2 * nv], Q[:nv], Q[nv:2 * nv] = V, V, N, -N
        bones = bone_transforms or {}
        for bone, where, pv, pn in self._parts:
            T = bones.get(bone)
            if T is None:
                P[where], Q[where] = pv, pn
                continue
            T = np.asarray(T, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"bone_transforms[{bone!r}]: expected a (4, 4) matrix, got shape {T.shape}")
            P[where] = pv @ T[:3, :3].T + T[:3, 3]
            Q[where] = pn @ T[:3, :3].T  # rigid: rotation only
        return P, Q

    def render(self, skin_vertices: np.ndarray | None = None,
               bone_transforms: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """One frame, (H, W, 3) uint8 RGB.

        skin_vertices    (V, 3) float metres, the deformed skin in world space; None: rest
        bone_transforms  bone name -> (4, 4) world transform (rest -> now) of the parts on
                         that bone ("head", "jaw", "eye_l", "eye_r", "tongue"); a bone not
                         given (or None) stays at rest
        """
        if self._closed:
            raise RuntimeError("FaceRenderer is closed")
        P, Q = self.frame_geometry(skin_vertices, bone_transforms)
        self._staging[:, :3] = P
        self._staging[:, 3:6] = Q
        self._platform.make_current()
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])  # the interleaved vertex buffer
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, self._staging.nbytes, self._staging)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        self._renderer.render(self._scene, self._flags)
        image = self._renderer.read_color_buf()
        k = self.supersample
        if k > 1:
            w, h = self.size
            blocks = image.reshape(h, k, w, k, 3).astype(np.uint16).sum(axis=(1, 3))
            return ((blocks + (k * k) // 2) // (k * k)).astype(np.uint8)
        return np.ascontiguousarray(image)

    def close(self) -> None:
        """Free the GL context and buffers; idempotent."""
        if getattr(self, "_closed", True):
            return
        self._closed = True
        self._platform.make_current()
        self._renderer.delete()
        self._platform.delete_context()

    def __enter__(self) -> "FaceRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
