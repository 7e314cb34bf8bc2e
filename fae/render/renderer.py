"""Headless frames of a FaceModel: the only module in fae that talks to OpenGL.

`FaceRenderer(model, size, view, supersample).render(skin_vertices, bone_transforms,
pupil_scale)` returns an (H, W, 3) uint8 RGB image.

What is drawn is what shows on a real face: the skin, the eyes, teeth and tongue, and the
mouth cavity (the skin's own inner side, dark, seen through the open mouth or any other
opening). The cranium and mandible are anatomy under the skin and are left out unless
`show_bones=True` (for looking at how the skin sits on the skull).

Everything the frame loop needs is made once in the constructor: one GL program (Blinn-
Phong lit per vertex with a key, fill and rim light, per-vertex colour and gloss, gamma
2.2), one static vertex buffer (colours, gloss), one index buffer and one dynamic buffer of
positions and normals. A frame computes skin normals, poses the rigid parts on the CPU
(widening or narrowing the pupils), writes the dynamic buffer with one `glBufferSubData`,
draws every outward-facing triangle, then the inside (the cavity colour) of the skin
triangles that can show it, and copies the OSMesa colour buffer, which is a numpy array
already (no `glReadPixels`). The projection flips y so rows come out top first. No GL
object is created per frame.

pyrender is used only for its headless GL platforms (OSMesa, EGL). Its scene renderer
(a physically based shader per pixel, about 1 ms of Python per primitive per frame) is
the baseline tools/bench_play.py measures this one against.
llvmpipe rasterizes with `LP_NUM_THREADS` threads; unless the environment sets it, it is
the usable core count less one, which is left to the simulation thread that `fae play`
overlaps with rendering (on 2 cores: 27.3 frames/s end to end against 23.8 with 2 render
threads contending with the simulation, tools/bench_play.py).
"""

from __future__ import annotations

import ctypes
import os

from fae.cores import usable_cores

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
os.environ.setdefault("LP_NUM_THREADS", str(max(1, usable_cores() - 1)))

import numpy as np  # noqa: E402
from OpenGL import GL  # noqa: E402

from fae.io.facemodel import FaceModel, Part  # noqa: E402
from fae.render.framing import MAX_RENDER_SIDE, VIEWS, CameraView, camera_view, head_frame  # noqa: E402
from fae.mesh import wrapped_seam  # noqa: E402
from fae.render.normals import per_vertex_normals  # noqa: E402

# Colours are linear RGB; the shader applies gamma 2.2. The background is used as-is.
BACKGROUND = (0.80, 0.82, 0.85)
CAVITY_COLOR = (0.05, 0.012, 0.014)  # inside of the mouth and head, seen through openings
MOUTH_COLOR = (0.10, 0.022, 0.025)  # the mouth's lining seen through the lips: mucosa in shade
MOUTH_REGION = "mouth_cavity"
MOUTH_BLEND_RINGS = 2  # edge rings over which the lips' inner side darkens into the mouth
BONE_COLOR = (0.80, 0.75, 0.62)  # cranium and mandible when shown
AMBIENT = 0.22
# Anatomy under the skin: not drawn unless show_bones.
HIDDEN_PARTS = ("cranium", "mandible")
# (specular weight, Blinn-Phong exponent) per part; wet eyes shine, skin barely.
GLOSS = {
    "skin": (0.10, 18.0),
    "cavity": (0.0, 1.0),
    "eye_l": (0.85, 90.0),
    "eye_r": (0.85, 90.0),
    "upper_teeth": (0.35, 40.0),
    "lower_teeth": (0.35, 40.0),
    "tongue": (0.30, 30.0),
}
_DEFAULT_GLOSS = (0.10, 20.0)

# Light rig in camera coordinates (x right, y up, +z towards the viewer): direction the
# light comes FROM, colour, and intensity. A warm key from the upper left, a cool softer
# fill from the right, a rim light from behind and above that separates the head from the
# background.
LIGHTS = (
    ((-0.55, 0.55, 1.0), (1.0, 0.97, 0.92), 1.0),
    ((0.85, 0.05, 0.8), (0.88, 0.92, 1.0), 0.42),
    ((0.2, 0.9, -0.9), (1.0, 1.0, 1.0), 0.5),
)
# A pupil never grows past this fraction of the iris (angles from the eye's axis).
_PUPIL_MAX_PER_IRIS = 0.85
_PUPIL_MIN_SCALE = 0.2

_VERTEX_SHADER = """
#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;
layout(location = 2) in vec3 color;
layout(location = 3) in vec2 gloss;
layout(location = 4) in vec3 texcoord;  // u, v and how much of the colour comes from the texture
uniform mat4 world_to_camera;
uniform mat4 projection;
uniform vec3 light_direction[%(lights)d];
uniform vec3 light_color[%(lights)d];
uniform float ambient;
out vec3 v_front;
out vec3 v_back;
out vec3 v_light;  // light reaching the surface (times albedo: the diffuse colour)
out vec3 v_specular;
out vec3 v_texcoord;

void main() {
    vec4 p = world_to_camera * vec4(position, 1.0);
    vec3 n = normalize(mat3(world_to_camera) * normal);
    vec3 to_eye = normalize(-p.xyz);
    v_light = vec3(ambient);
    v_specular = vec3(0.0);
    for (int i = 0; i < %(lights)d; ++i) {
        float d = dot(n, light_direction[i]);
        if (d > 0.0) {
            vec3 h = normalize(light_direction[i] + to_eye);
            v_light += light_color[i] * d;
            v_specular += light_color[i] * gloss.x * pow(max(dot(n, h), 0.0), gloss.y);
        }
    }
    v_front = pow(clamp(color * v_light + v_specular, 0.0, 1.0), vec3(1.0 / 2.2));
    v_texcoord = texcoord;
    // The inside: mostly its own dark colour, a little shape from the key light.
    v_back = pow(vec3(%(cavity)s) * (0.6 + 0.6 * max(dot(-n, light_direction[0]), 0.0)), vec3(1.0 / 2.2));
    gl_Position = projection * p;
}
"""

# Lit per vertex (a skin triangle covers a few pixels at video sizes, so this matches
# per-pixel lighting closely, and llvmpipe's fragment work drops to a copy). A triangle
# seen from behind is the inside of the head: it gets the cavity colour.
_FRAGMENT_SHADER = """
#version 330 core
in vec3 v_front;
in vec3 v_back;
out vec4 frag_color;
void main() {
    frag_color = vec4(gl_FrontFacing ? v_front : v_back, 1.0);
}
"""

# A skin with a texture (a photo's colours): the albedo is looked up per pixel, the light
# still comes per vertex; where the texture weight is 0 (rigid parts, inside the mouth) the
# colour is exactly the untextured one.
_TEXTURED_FRAGMENT_SHADER = """
#version 330 core
in vec3 v_front;
in vec3 v_back;
in vec3 v_light;
in vec3 v_specular;
in vec3 v_texcoord;
uniform sampler2D skin_texture;
out vec4 frag_color;
void main() {
    if (!gl_FrontFacing) {
        frag_color = vec4(v_back, 1.0);
        return;
    }
    vec3 albedo = pow(texture(skin_texture, v_texcoord.xy).rgb, vec3(2.2));
    vec3 lit = pow(clamp(albedo * v_light + v_specular, 0.0, 1.0), vec3(1.0 / 2.2));
    frag_color = vec4(mix(v_front, lit, clamp(v_texcoord.z, 0.0, 1.0)), 1.0);
}
"""


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


def _compile_program(vertex_source: str, fragment_source: str) -> int:
    shaders = []
    for kind, source in ((GL.GL_VERTEX_SHADER, vertex_source), (GL.GL_FRAGMENT_SHADER, fragment_source)):
        shader = GL.glCreateShader(kind)
        GL.glShaderSource(shader, source)
        GL.glCompileShader(shader)
        if not GL.glGetShaderiv(shader, GL.GL_COMPILE_STATUS):
            raise RuntimeError(f"shader compilation failed: {GL.glGetShaderInfoLog(shader).decode(errors='replace')}")
        shaders.append(shader)
    program = GL.glCreateProgram()
    for shader in shaders:
        GL.glAttachShader(program, shader)
    GL.glLinkProgram(program)
    if not GL.glGetProgramiv(program, GL.GL_LINK_STATUS):
        raise RuntimeError(f"shader link failed: {GL.glGetProgramInfoLog(program).decode(errors='replace')}")
    for shader in shaders:
        GL.glDetachShader(program, shader)
        GL.glDeleteShader(shader)
    return program


def skin_colors(model: FaceModel) -> np.ndarray:
    """(V, 3) float32 linear RGB of the skin's vertices: the skin colour, and inside the mouth
    (the skin region MOUTH_REGION, where the head has one) the lining's darker colour,
    blended over MOUTH_BLEND_RINGS edge rings so that the lips' inner side darkens into it."""
    skin = np.asarray(model.skin_color, dtype=np.float32).reshape(-1)[:3]
    w = mouth_weight(model)
    mouth = np.asarray(MOUTH_COLOR, dtype=np.float32)
    return (skin[None, :] * (1.0 - w[:, None]) + mouth[None, :] * w[:, None]).astype(np.float32)


def mouth_weight(model: FaceModel) -> np.ndarray:
    """(V,) float64 in [0, 1]: 1 inside the mouth (the skin region MOUTH_REGION), falling
    to 0 over MOUTH_BLEND_RINGS edge rings around it; zeros when the head has no such region."""
    nv = len(model.skin_vertices)
    names = list(model.region_names)
    region = np.asarray(model.skin_region)
    if MOUTH_REGION not in names or region.shape != (nv,):
        return np.zeros(nv)
    w = (region == names.index(MOUTH_REGION)).astype(np.float64)
    faces = np.asarray(model.skin_faces, dtype=np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    valence = np.bincount(e[:, 0], minlength=nv) + np.bincount(e[:, 1], minlength=nv)
    for _ in range(MOUTH_BLEND_RINGS):
        mean = (np.bincount(e[:, 0], weights=w[e[:, 1]], minlength=nv)
                + np.bincount(e[:, 1], weights=w[e[:, 0]], minlength=nv)) / np.maximum(valence, 1)
        w = np.maximum(w, mean)
    return w


MAX_HOLE_BOXES = 64  # holes whose screen boxes are tested per frame; more: all inside triangles drawn


def boundary_components(F: np.ndarray, n: int) -> list[np.ndarray]:
    """The holes of a triangle mesh: one (k,) int64 array of vertex indices per connected
    set of boundary edges (edges used by one triangle). F (m, 3) int, n vertex count."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1).astype(np.int64)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    if len(boundary) == 0:
        return []
    graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    on_boundary = np.unique(boundary)
    order = np.argsort(label[on_boundary], kind="stable")
    grouped = on_boundary[order]
    splits = np.nonzero(np.diff(label[grouped]))[0] + 1
    return list(np.split(grouped, splits))


def perspective(yfov: float, aspect: float, znear: float, zfar: float) -> np.ndarray:
    """(4, 4) float64 OpenGL projection matrix (camera looks along -z)."""
    f = 1.0 / np.tan(0.5 * yfov)
    P = np.zeros((4, 4))
    P[0, 0], P[1, 1] = f / aspect, f
    P[2, 2] = (zfar + znear) / (znear - zfar)
    P[2, 3] = 2.0 * zfar * znear / (znear - zfar)
    P[3, 2] = -1.0
    return P


class _PupilRig:
    """Widens or narrows one eye's pupil by turning its vertices about the eye centre.

    Vertices are moved along the eyeball, away from or towards the eye's axis (centre ->
    pupil): the pupil's angular radius is multiplied by the scale, the iris ring between
    pupil and limbus is stretched or squeezed to fit, and the limbus and the white stay
    where they are. Vertex colours do not change; the dark pupil colour goes with its
    vertices.

    centre (3,) metres; axis (3,) unit; index (k,) vertices of the part inside the iris;
    radial (k, 3) unit directions away from the axis; angle (k,) radians from the axis.
    """

    def __init__(self, vertices: np.ndarray, colors: np.ndarray, base_color: np.ndarray, centre: np.ndarray):
        luminance = colors[:, :3] @ np.array([0.2126, 0.7152, 0.0722])
        pupil = luminance < 0.05
        iris = np.abs(colors[:, :3] - base_color[:3]).max(axis=1) > 0.05
        if not pupil.any() or pupil.all() or not iris.any():
            raise ValueError("no pupil")
        self.centre = centre
        axis = (vertices[pupil] - centre).mean(axis=0)
        self.axis = axis / np.linalg.norm(axis)
        d = vertices - centre
        along = d @ self.axis
        angle = np.arctan2(np.linalg.norm(d - along[:, None] * self.axis, axis=1), along)
        self.pupil_angle = float(angle[pupil].max())
        self.iris_angle = float(angle[iris].max())
        if not 0.0 < self.pupil_angle < self.iris_angle:
            raise ValueError("pupil not inside the iris")
        self.index = np.nonzero(angle <= self.iris_angle)[0]
        d = d[self.index]
        radial = d - (d @ self.axis)[:, None] * self.axis
        length = np.linalg.norm(radial, axis=1)
        length[length < 1e-12] = 1.0
        self.radial = radial / length[:, None]
        self.angle = angle[self.index]
        self.max_scale = _PUPIL_MAX_PER_IRIS * self.iris_angle / self.pupil_angle

    def turn(self, scale: float) -> np.ndarray | None:
        """(k,) radians each iris vertex turns away from the axis for `scale`, or None at 1."""
        s = float(np.clip(scale, _PUPIL_MIN_SCALE, self.max_scale))
        if s == 1.0:
            return None
        p, i, a = self.pupil_angle, self.iris_angle, self.angle
        new = np.where(a <= p, a * s, i - (i - a) * (i - s * p) / (i - p))
        return new - a

    def apply(self, scale: float, P: np.ndarray, N: np.ndarray) -> None:
        """Move the iris vertices of rest positions P and normals N (n, 3) in place."""
        delta = self.turn(scale)
        if delta is None:
            return
        c, s = np.cos(delta)[:, None], np.sin(delta)[:, None]
        a, r = self.axis, self.radial
        for X, origin in ((P, self.centre), (N, 0.0)):
            x = X[self.index] - origin
            xa, xr = x @ a, np.einsum("ij,ij->i", x, r)
            rest = x - xa[:, None] * a - xr[:, None] * r  # the part along the rotation axis
            X[self.index] = origin + rest + (c[:, 0] * xa - s[:, 0] * xr)[:, None] * a \
                + (s[:, 0] * xa + c[:, 0] * xr)[:, None] * r


class FaceRenderer:
    """Renders one FaceModel, frame after frame, into RGB images.

    model        the head (skin + rigid parts); never modified
    size         (width, height) of the output image, pixels
    view         "front", "three-quarter" or "profile" (camera framed from the head's
                 feature points, see fae.render.framing)
    supersample  k >= 1: render at k x size and average k x k blocks (anti-aliasing; OSMesa
                 has no multisampling). Costs about k^2 in fragment work.
    background   linear RGB floats in [0, 1], used as-is
    show_bones   also draw the cranium and mandible (hidden under the skin on a real face)
    camera       a CameraView to use instead of the `view` preset framed on this head (to
                 draw two heads, or a head and a scan, from one camera)
    normal_groups  (V,) int labels: skin vertices with the same label share one normal (a
                 mesh split along its texture seams: each side of a seam lit by its own
                 triangles alone shows the seam as a crease); None: every vertex its own
    skin_rgb     (V, 3) linear RGB of the skin's vertices instead of its own colours (to
                 mark some of them); a texture, where the head has one, is drawn over it

    Use as a context manager or call `close()` to free the GL context.
    """

    def __init__(self, model: FaceModel, size: tuple[int, int] = (640, 480), view: str = "front",
                 supersample: int = 1, background=BACKGROUND, show_bones: bool = False,
                 camera: CameraView | None = None, normal_groups: np.ndarray | None = None,
                 skin_rgb: np.ndarray | None = None):
        width, height = (int(s) for s in size)
        if width <= 0 or height <= 0:
            raise ValueError(f"image size {width}x{height}: expected positive width and height")
        if int(supersample) != supersample or supersample < 1:
            raise ValueError(f"supersample {supersample!r}: expected an integer >= 1")
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}: expected one of {', '.join(VIEWS)}")
        bg = np.asarray(background, dtype=np.float64).reshape(-1)
        if bg.size < 3 or not np.all((bg[:3] >= 0.0) & (bg[:3] <= 1.0)):
            raise ValueError(f"background {background!r}: expected linear RGB floats in [0, 1]")
        self.model = model
        self.size = (width, height)
        self.supersample = int(supersample)
        self.view = view
        self.show_bones = bool(show_bones)
        self._vw, self._vh = width * self.supersample, height * self.supersample
        if max(self._vw, self._vh) > MAX_RENDER_SIDE:
            raise ValueError(f"image size {width}x{height} at supersample {self.supersample} is drawn "
                             f"{self._vw}x{self._vh}: expected at most {MAX_RENDER_SIDE} pixels a side")
        self.camera: CameraView = camera_view(model, view, aspect=width / height) if camera is None else camera
        self._background = tuple(float(c) for c in bg[:3])

        rest = np.asarray(model.skin_vertices, dtype=np.float64)
        faces = np.asarray(model.skin_faces, dtype=np.int64)
        if rest.ndim != 2 or rest.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"skin: expected vertices (V, 3) and faces (F, 3), got {rest.shape} and {faces.shape}")
        nv = rest.shape[0]
        self._skin_rest = rest
        self._skin_faces = faces
        self._normal_groups = None
        if normal_groups is not None:
            groups = np.asarray(normal_groups, dtype=np.int64)
            if groups.shape != (rest.shape[0],) or (len(groups) and (groups.min() < 0 or groups.max() >= len(groups))):
                raise ValueError(f"normal_groups: expected ({rest.shape[0]},) labels in [0, {rest.shape[0]})")
            self._normal_groups = groups
        self._corner_index = faces.ravel() if self._normal_groups is None else self._normal_groups[faces].ravel()
        self._skin_rest_normals = self._skin_normals(rest)

        # A textured skin: its texture coordinates wrap around the head, so the vertices of
        # the triangles that cross the seam are drawn twice (copies with u + 1, `_seam_source`),
        # and the inside of the mouth keeps its own colour (texture weight 0).
        texture = getattr(model, "skin_texture", None)
        self._texture_image = None
        self._seam_source = np.zeros(0, dtype=np.int64)
        self._skin_draw_faces = faces
        texcoord = np.zeros((nv, 3), dtype=np.float32)
        if texture is not None:
            texture = np.asarray(texture)
            if texture.ndim != 3 or texture.shape[2] != 3 or texture.dtype != np.uint8 or min(texture.shape[:2]) < 1:
                raise ValueError(f"skin_texture: expected an (H, W, 3) uint8 image, got {texture.dtype} {texture.shape}")
            uv = np.asarray(model.skin_uv, dtype=np.float32)
            if uv.shape != (nv, 2):
                raise ValueError(f"skin_uv: expected shape {(nv, 2)} for the texture, got {uv.shape}")
            self._texture_image = np.ascontiguousarray(texture)
            self._skin_draw_faces, self._seam_source, uv2 = wrapped_seam(faces, uv)
            weight = (1.0 - mouth_weight(model)).astype(np.float32)
            weight = np.concatenate([weight, weight[self._seam_source]])
            texcoord = np.concatenate([uv2, weight[:, None]], axis=1).astype(np.float32)
        skin_count = nv + len(self._seam_source)  # skin vertices drawn, seam copies included
        self._skin_count = skin_count

        # Vertex arrays: the skin, then each drawn rigid part. The skin's inner side (the
        # cavity) is the same vertices drawn again with front faces culled.
        skin_rgb = skin_colors(model) if skin_rgb is None else np.asarray(skin_rgb, dtype=np.float32)
        if skin_rgb.shape != (nv, 3):
            raise ValueError(f"skin_rgb: expected ({nv}, 3) linear RGB, got {skin_rgb.shape}")
        colors = [np.concatenate([skin_rgb, skin_rgb[self._seam_source]])]
        gloss = [np.tile(np.asarray(GLOSS["skin"], dtype=np.float32), (skin_count, 1))]
        texcoords = [texcoord]
        tris = [self._skin_draw_faces]
        offset = skin_count
        self._parts = []  # (bone, slice into the vertex arrays, rest vertices, rest normals, pupil rig)
        for name, part in model.parts.items():
            pv = np.asarray(part.vertices, dtype=np.float64)
            pf = np.asarray(part.faces, dtype=np.int64)
            if pv.size == 0 or pf.size == 0 or (name in HIDDEN_PARTS and not self.show_bones):
                continue
            pc = self._part_colors(name, part)
            pupil = None
            if part.vertex_colors is not None and part.bone in model.eye_centers:
                try:
                    pupil = _PupilRig(pv, pc, np.asarray(part.color, dtype=np.float32).reshape(-1),
                                      np.asarray(model.eye_centers[part.bone], dtype=np.float64))
                except ValueError:
                    pupil = None  # an eye without a pupil colour: drawn, never dilated
            colors.append(pc[:, :3])
            part_gloss = np.tile(np.asarray(GLOSS.get(name, _DEFAULT_GLOSS), dtype=np.float32), (len(pv), 1))
            if part.vertex_colors is not None and pupil is None:
                # where a part is painted darker than its colour (the teeth towards the back
                # of the arch, in the cheeks' shade) it shines as much less
                base = float(np.mean(np.asarray(part.color, dtype=np.float32).reshape(-1)[:3]))
                part_gloss[:, 0] *= np.clip(pc[:, :3].mean(axis=1) / max(base, 1e-6), 0.0, 1.0)
            gloss.append(part_gloss)
            texcoords.append(np.zeros((len(pv), 3), dtype=np.float32))
            tris.append(pf + offset)
            self._parts.append((part.bone, slice(offset, offset + len(pv)), pv, per_vertex_normals(pv, pf), pupil))
            offset += len(pv)
        self.vertex_count = offset
        self.vertex_colors = np.concatenate(colors).astype(np.float32)  # (vertex_count, 3) linear RGB
        self.triangles = np.concatenate(tris).astype(np.uint32)  # (m, 3) into the frame_geometry arrays
        self._skin_index_count = 3 * len(faces)
        self._index_count = 3 * sum(len(t) for t in tris)
        # The skin's inside shows where the skin folds over (lips parting on a closed skin)
        # and through its holes (mouth, neck, the open back of a face scan). Each frame
        # draws the inside of just the triangles that face away from the camera and either
        # lie on the near half of the head or overlap a hole on screen (bounding boxes):
        # the far half's inside, hidden behind the face, costs the rasterizer as much as
        # the whole outside.
        holes = boundary_components(faces, nv)
        # a mesh of many loose pieces (an STL triangle soup, hair cards) has a hole per piece:
        # testing every triangle against each hole's box cost a second a frame for 22k
        # triangles (a minute for 90k); beyond MAX_HOLE_BOXES every inside triangle is drawn
        self._holes = holes if len(holes) <= MAX_HOLE_BOXES else None
        # Per frame: positions and normals, float32, interleaved.
        self._dynamic = np.empty((offset, 6), dtype=np.float32)
        static = np.concatenate([self.vertex_colors, np.concatenate(gloss), np.concatenate(texcoords)],
                                axis=1).astype(np.float32)
        indices = self.triangles

        self._platform = _make_platform(self._vw, self._vh)
        self._closed = False
        self._make_gl_objects(static, indices)

    @staticmethod
    def _part_colors(name: str, part: Part) -> np.ndarray:
        if name in HIDDEN_PARTS:
            return np.tile(np.array([*BONE_COLOR, 1.0], dtype=np.float32), (len(part.vertices), 1))
        if part.vertex_colors is not None:
            return np.asarray(part.vertex_colors, dtype=np.float32).reshape(-1, 4)
        return np.tile(np.asarray(part.color, dtype=np.float32).reshape(4), (len(part.vertices), 1))

    def _make_gl_objects(self, static: np.ndarray, indices: np.ndarray) -> None:
        cavity = ", ".join(f"{c:.6f}" for c in CAVITY_COLOR)
        self._program = _compile_program(_VERTEX_SHADER % {"cavity": cavity, "lights": len(LIGHTS)},
                                          _FRAGMENT_SHADER if self._texture_image is None
                                          else _TEXTURED_FRAGMENT_SHADER)
        self._vao = GL.glGenVertexArrays(1)
        GL.glBindVertexArray(self._vao)
        self._buffers = GL.glGenBuffers(3)
        dynamic_buffer, static_buffer, index_buffer = (int(b) for b in self._buffers)
        self._dynamic_buffer = dynamic_buffer
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, dynamic_buffer)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, self._dynamic.nbytes, None, GL.GL_STREAM_DRAW)
        for location, start in ((0, 0), (1, 3)):
            GL.glEnableVertexAttribArray(location)
            GL.glVertexAttribPointer(location, 3, GL.GL_FLOAT, GL.GL_FALSE, 24, ctypes.c_void_p(4 * start))
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, static_buffer)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, static.nbytes, np.ascontiguousarray(static), GL.GL_STATIC_DRAW)
        for location, count, start in ((2, 3, 0), (3, 2, 3), (4, 3, 5)):
            GL.glEnableVertexAttribArray(location)
            GL.glVertexAttribPointer(location, count, GL.GL_FLOAT, GL.GL_FALSE, 32, ctypes.c_void_p(4 * start))
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, index_buffer)
        # All triangles, then room for the inside triangles chosen each frame.
        GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, indices.nbytes + 4 * self._skin_index_count, None,
                        GL.GL_DYNAMIC_DRAW)
        GL.glBufferSubData(GL.GL_ELEMENT_ARRAY_BUFFER, 0, indices.nbytes, indices)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        self._texture = None
        if self._texture_image is not None:
            self._texture = int(GL.glGenTextures(1))
            GL.glActiveTexture(GL.GL_TEXTURE0)
            GL.glBindTexture(GL.GL_TEXTURE_2D, self._texture)
            GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
            h, w = self._texture_image.shape[:2]
            # rows go up in order, the first at t = 0: glTF's convention (v = 0 on the first row)
            GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGB8, w, h, 0, GL.GL_RGB, GL.GL_UNSIGNED_BYTE,
                            self._texture_image)
            GL.glGenerateMipmap(GL.GL_TEXTURE_2D)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_WRAP_S, GL.GL_REPEAT)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_WRAP_T, GL.GL_CLAMP_TO_EDGE)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR_MIPMAP_LINEAR)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_LINEAR)

        GL.glUseProgram(self._program)
        if self._texture is not None:
            GL.glUniform1i(GL.glGetUniformLocation(self._program, "skin_texture"), 0)
        world_to_camera = np.linalg.inv(self.camera.pose)
        # Depth up to which the inside of skin facing away may show: the head centre, plus a
        # little for folds on the silhouette (the neck behind a turned or opened jaw).
        self._target_distance = float(np.linalg.norm(self.camera.pose[:3, 3] - self.camera.target)) \
            + 0.25 * head_frame(self.model).depth
        self._world_to_clip = (perspective(self.camera.yfov, self.size[0] / self.size[1], self.camera.znear,
                                           self.camera.zfar) @ world_to_camera)
        # y flipped: rows come out of GL top row first, as images are stored. That mirrors
        # the winding on screen, so front faces are the clockwise ones.
        projection = np.diag([1.0, -1.0, 1.0, 1.0]) @ perspective(
            self.camera.yfov, self.size[0] / self.size[1], self.camera.znear, self.camera.zfar)
        location = GL.glGetUniformLocation
        GL.glUniformMatrix4fv(location(self._program, "world_to_camera"), 1, GL.GL_TRUE,
                              world_to_camera.astype(np.float32))
        GL.glUniformMatrix4fv(location(self._program, "projection"), 1, GL.GL_TRUE, projection.astype(np.float32))
        directions = np.array([np.asarray(d) / np.linalg.norm(d) for d, _, _ in LIGHTS], dtype=np.float32)
        light_colors = np.array([np.asarray(c) * i for _, c, i in LIGHTS], dtype=np.float32)
        GL.glUniform3fv(location(self._program, "light_direction"), len(LIGHTS), directions)
        GL.glUniform3fv(location(self._program, "light_color"), len(LIGHTS), light_colors)
        GL.glUniform1f(location(self._program, "ambient"), AMBIENT)
        GL.glViewport(0, 0, self._vw, self._vh)
        GL.glClearColor(*self._background, 1.0)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glEnable(GL.GL_CULL_FACE)
        GL.glFrontFace(GL.GL_CW)
        GL.glDisable(GL.GL_BLEND)

    def frame_geometry(self, skin_vertices=None, bone_transforms=None,
                       pupil_scale=None) -> tuple[np.ndarray, np.ndarray]:
        """(positions, normals), each (vertex_count, 3) float32, of everything drawn in one
        frame: the skin, then each drawn rigid part posed by its bone (see `render`)."""
        self._write_geometry(skin_vertices, bone_transforms, pupil_scale)
        return self._dynamic[:, :3].copy(), self._dynamic[:, 3:].copy()

    def _write_geometry(self, skin_vertices, bone_transforms, pupil_scale) -> None:
        """Fill the (vertex_count, 6) float32 staging array of positions and normals."""
        if skin_vertices is None:
            V, N = self._skin_rest, self._skin_rest_normals
        else:
            V = np.asarray(skin_vertices, dtype=np.float64)
            if V.shape != self._skin_rest.shape:
                raise ValueError(f"skin_vertices: expected shape {self._skin_rest.shape}, got {V.shape}")
            N = self._skin_normals(V)
        out = self._dynamic
        nv = V.shape[0]
        out[:nv, :3] = V
        out[:nv, 3:] = N
        if len(self._seam_source):
            out[nv:self._skin_count, :3] = V[self._seam_source]
            out[nv:self._skin_count, 3:] = N[self._seam_source]
        bones = bone_transforms or {}
        pupils = pupil_scale or {}
        for bone, where, pv, pn, pupil in self._parts:
            scale = pupils.get(bone)
            if pupil is not None and scale is not None and pupil.turn(scale) is not None:
                pv, pn = pv.copy(), pn.copy()
                pupil.apply(scale, pv, pn)
            T = bones.get(bone)
            if T is None:
                out[where, :3], out[where, 3:] = pv, pn
                continue
            T = np.asarray(T, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"bone_transforms[{bone!r}]: expected a (4, 4) matrix, got shape {T.shape}")
            out[where, :3] = pv @ T[:3, :3].T + T[:3, 3]
            out[where, 3:] = pn @ T[:3, :3].T  # rigid: rotation only

    def _skin_normals(self, V: np.ndarray) -> np.ndarray:
        """(V, 3) unit normals of the skin at positions V, shared within normal_groups."""
        N = per_vertex_normals(V, self._skin_faces, self._corner_index)
        return N if self._normal_groups is None else N[self._normal_groups]

    def render(self, skin_vertices: np.ndarray | None = None,
               bone_transforms: dict[str, np.ndarray] | None = None,
               pupil_scale: dict[str, float] | None = None) -> np.ndarray:
        """One frame, (H, W, 3) uint8 RGB.

        skin_vertices    (V, 3) float metres, the deformed skin in world space; None: rest
        bone_transforms  bone name -> (4, 4) world transform (rest -> now) of the parts on
                         that bone ("head", "jaw", "eye_l", "eye_r", "tongue"); a bone not
                         given (or None) stays at rest
        pupil_scale      eye bone ("eye_l", "eye_r") -> pupil diameter / rest diameter
                         (MPEG-4 FAPs 29, 30); kept between 0.2 and what the iris holds
        """
        return np.ascontiguousarray(self.render_rgba(skin_vertices, bone_transforms, pupil_scale)[:, :, :3])

    def render_rgba(self, skin_vertices: np.ndarray | None = None,
                    bone_transforms: dict[str, np.ndarray] | None = None,
                    pupil_scale: dict[str, float] | None = None) -> np.ndarray:
        """One frame, (H, W, 4) uint8 RGBA (alpha 255), as `render` but without dropping
        the alpha channel: the GL colour buffer is RGBA, and copying 3 of every 4 bytes
        costs more than the copy itself (ffmpeg and Pillow take RGBA as it is)."""
        if self._closed:
            raise RuntimeError("FaceRenderer is closed")
        self._write_geometry(skin_vertices, bone_transforms, pupil_scale)
        self._platform.make_current()
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._dynamic_buffer)
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, self._dynamic.nbytes, self._dynamic)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        GL.glUseProgram(self._program)
        GL.glBindVertexArray(self._vao)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        inside = self._inside_triangles()
        if len(inside):
            GL.glBufferSubData(GL.GL_ELEMENT_ARRAY_BUFFER, 4 * self._index_count, inside.nbytes, inside)
        GL.glCullFace(GL.GL_BACK)
        GL.glDrawElements(GL.GL_TRIANGLES, self._index_count, GL.GL_UNSIGNED_INT, None)
        if len(inside):
            GL.glCullFace(GL.GL_FRONT)
            GL.glDrawElements(GL.GL_TRIANGLES, inside.size, GL.GL_UNSIGNED_INT, ctypes.c_void_p(4 * self._index_count))
        GL.glFinish()
        image = self._color_buffer()
        k = self.supersample
        if k > 1:
            w, h = self.size
            blocks = image.reshape(h, k, w, k, 4).astype(np.uint16).sum(axis=(1, 3))
            return ((blocks + (k * k) // 2) // (k * k)).astype(np.uint8)
        return image

    def _inside_triangles(self) -> np.ndarray:
        """(k, 3) uint32 skin triangles of this frame whose inside may show (see __init__)."""
        nv = len(self._skin_rest)
        V = self._dynamic[:nv, :3]
        M = self._world_to_clip.astype(np.float32)
        w = V @ M[3, :3] + M[3, 3]  # distance in front of the camera
        if w.min() <= 1e-6:  # something behind the camera: keep every inside triangle
            return self._skin_faces.astype(np.uint32)
        xy = (V @ M[:2, :3].T + M[:2, 3]) / w[:, None]
        F = self._skin_faces
        a, b, c = xy[F[:, 0]], xy[F[:, 1]], xy[F[:, 2]]
        # Counter-clockwise seen from outside; negative area on screen: facing away.
        away = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0.0
        if self._holes is None:  # too many holes to test: every inside triangle may show
            return np.ascontiguousarray(self._skin_draw_faces[away], dtype=np.uint32)
        seen = w[F].min(axis=1) < self._target_distance
        if self._holes:
            lo = np.minimum(np.minimum(a, b), c)
            hi = np.maximum(np.maximum(a, b), c)
            margin = 4.0 / min(self._vw, self._vh)  # a couple of pixels, in NDC
            for hole in self._holes:
                hlo, hhi = xy[hole].min(axis=0) - margin, xy[hole].max(axis=0) + margin
                seen |= (lo[:, 0] <= hhi[0]) & (hi[:, 0] >= hlo[0]) & (lo[:, 1] <= hhi[1]) & (hi[:, 1] >= hlo[1])
        return np.ascontiguousarray(self._skin_draw_faces[away & seen], dtype=np.uint32)

    def _color_buffer(self) -> np.ndarray:
        """(vh, vw, 4) uint8 copy of the rendered colour buffer, top row first (the
        projection flips y, so GL's first row is the image's top row)."""
        buffer = getattr(self._platform, "_buffer", None)
        if buffer is not None:  # OSMesa renders straight into this array
            return np.array(buffer, dtype=np.uint8, copy=True).reshape(self._vh, self._vw, 4)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        data = GL.glReadPixels(0, 0, self._vw, self._vh, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE)
        return np.frombuffer(data, dtype=np.uint8).reshape(self._vh, self._vw, 4).copy()

    def close(self) -> None:
        """Free the GL objects and context; idempotent."""
        if getattr(self, "_closed", True):
            return
        self._closed = True
        self._platform.make_current()
        GL.glDeleteBuffers(3, self._buffers)
        if getattr(self, "_texture", None) is not None:
            GL.glDeleteTextures([self._texture])
        GL.glDeleteVertexArrays(1, [self._vao])
        GL.glDeleteProgram(self._program)
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
