"""A head as a plain glTF 2.0 scene that any viewer opens and plays (three.js, Blender, ...).

Unlike the FaceModel file (fae.io.facemodel_gltf), nothing here is for fae to read back:

    head_bone                      rotates about feature point 7.1 (FAPs 48-50)
    ├── skin                       mesh with the skin's vertex colours and morph targets
    ├── upper_teeth                mesh (and every other part carried by the head bone)
    ├── eye_l_bone ── eye_l        yaw, pitch and thrust of each eyeball (FAPs 23-28)
    ├── eye_r_bone ── eye_r
    └── jaw_bone                   the mandible's hinge rotation and glide (FAPs 3, 14, 15)
        ├── lower_teeth
        └── tongue_bone ── tongue  the tongue's pose (43-47; its roll as an x scale)

The skull and mandible (inside the skin, never seen) are left out. Bone nodes carry the
Player's bone transforms (rest -> now, face frame) made local to their parent; at rest
every node is the identity and the meshes sit where the head has them (metres, +Y up,
the face looking along +Z: glTF's own axes). Morph targets are sparse accessors (only
the vertices a target moves are stored; whole ones where it moves most of them), named in `mesh.extras.targetNames`. With
keyframes, one animation holds the skin's morph weights and every bone node's
translation, rotation (and scale where it ever differs from 1), LINEAR, one key per frame.

    scene_glb(model, targets=..., skin_colors=..., keyframes=...) -> bytes
    write_scene(path, model, ...)                                    # atomic
"""

from __future__ import annotations

import os

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from fae.io.atomic import atomic_path
from fae.io.facemodel_gltf import (DEFAULT_ROUGHNESS, ROUGHNESS, png_bytes, texture_factors, vertex_normals,
                                   wrapped_texture)
from fae.mesh import seamed_surface

GENERATOR = "fae scene export"
HIDDEN_PARTS = ("cranium", "mandible")  # under the skin: never seen, left out
BONE_PARENTS = {"head": None, "eye_l": "head", "eye_r": "head", "jaw": "head", "tongue": "jaw"}
_ALIGNMENT = 8
_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963


class _Target:
    """A morph target as the writer takes it: name, vertices (k,), displacement (k, 3)."""

    def __init__(self, name: str, vertices: np.ndarray, displacement: np.ndarray):
        self.name, self.vertices, self.displacement = name, vertices, displacement


def local_transforms(bone_transforms: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Bone name -> (N, 4, 4) transforms relative to its parent in BONE_PARENTS, from the
    Player's (N, 4, 4) transforms in the face frame (a missing bone is the identity)."""
    count = len(next(iter(bone_transforms.values()))) if bone_transforms else 0
    absolute = {b: np.asarray(bone_transforms.get(b, np.tile(np.eye(4), (count, 1, 1))), dtype=np.float64)
                for b in BONE_PARENTS}
    return {b: absolute[b] if parent is None else np.linalg.solve(absolute[parent], absolute[b])
            for b, parent in BONE_PARENTS.items()}


def decompose(transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(translation (N, 3), rotation (N, 4) unit quaternions x y z w, scale (N, 3)) of
    (N, 4, 4) transforms M = T R S (glTF's order); quaternion signs kept continuous."""
    A = transforms[:, :3, :3]
    scale = np.linalg.norm(A, axis=1)  # column norms: A = R diag(s)
    R = A / scale[:, None, :]
    quaternions = Rotation.from_matrix(R).as_quat()
    for i in range(1, len(quaternions)):  # LINEAR keys take the short way between neighbours
        if quaternions[i] @ quaternions[i - 1] < 0.0:
            quaternions[i] = -quaternions[i]
    return transforms[:, :3, 3].copy(), quaternions, scale


def scene_glb(model, targets=(), skin_colors: np.ndarray | None = None, keyframes=None,
              name: str | None = None) -> bytes:
    """The .glb bytes of the scene (see module docstring).

    model        fae.io.facemodel.FaceModel
    targets      morph targets of the skin: objects with `name`, `vertices` (k,) increasing
                 indices and `displacement` (k, 3) metres at weight 1 (fae.animate.morphs)
    skin_colors  (V, 3) or (V, 4) linear RGB(A) of the skin's vertices (None: its colour)
    keyframes    None, or an object with `times` (N,) seconds, strictly increasing from 0,
                 `weights` (N, len(targets)) and `bone_transforms` {bone: (N, 4, 4)} in the
                 face frame (fae.animate.morphs.Keyframes)
    """
    return _SceneWriter(model, list(targets), skin_colors, keyframes, name).glb()


def write_scene(path: str | os.PathLike, model, **kwargs) -> None:
    """Write `scene_glb(model, **kwargs)` to `path`; the file appears only when complete."""
    data = scene_glb(model, **kwargs)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


class _SceneWriter:
    def __init__(self, model, targets, skin_colors, keyframes, name):
        self.model, self.targets, self.keyframes = model, targets, keyframes
        self.skin_colors = skin_colors
        self.name = name or (model.meta.get("name") if isinstance(model.meta, dict) else None) or "face"
        self.gltf = pygltflib.GLTF2()
        self.blob = bytearray()

    def view(self, data: bytes, target: int | None = None) -> int:
        self.blob += b"\0" * (-len(self.blob) % _ALIGNMENT)
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data),
                                                          target=target))
        self.blob += data
        return len(self.gltf.bufferViews) - 1

    def accessor(self, values: np.ndarray, component: int, kind: str, target: int | None = None,
                 bounds: bool = False) -> int:
        values = np.ascontiguousarray(values)
        acc = pygltflib.Accessor(bufferView=self.view(values.tobytes(), target), componentType=component,
                                 count=int(values.shape[0]), type=kind)
        if bounds:
            flat = values.reshape(values.shape[0], -1)
            acc.min = [float(v) for v in flat.min(axis=0)]
            acc.max = [float(v) for v in flat.max(axis=0)]
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def sparse_target(self, vertex_count: int, vertices: np.ndarray, displacement: np.ndarray) -> int:
        """A POSITION morph target: zero except `displacement` (k, 3) at `vertices` (k,);
        stored sparse, or whole where it moves most vertices (a sparse entry costs 16 bytes,
        a whole one 12: a played mesh's principal shapes move every vertex)."""
        values = np.asarray(displacement, dtype=np.float32)
        if len(values) > 0.75 * vertex_count:
            whole = np.zeros((vertex_count, 3), np.float32)
            whole[np.asarray(vertices, dtype=np.int64)] = values
            return self.accessor(whole, pygltflib.FLOAT, pygltflib.VEC3, _ARRAY_BUFFER, True)
        # bounds of the whole accessor: the vertices not listed are 0
        every = np.concatenate([values, np.zeros((1 if len(values) < vertex_count else 0, 3), np.float32)])
        full_min, full_max = every.min(axis=0), every.max(axis=0)
        acc = pygltflib.Accessor(componentType=pygltflib.FLOAT, count=vertex_count, type=pygltflib.VEC3, byteOffset=None,
                                 min=[float(v) for v in full_min], max=[float(v) for v in full_max])
        if len(values):
            acc.sparse = pygltflib.Sparse(
                count=len(values),
                indices=pygltflib.AccessorSparseIndices(
                    bufferView=self.view(np.asarray(vertices, dtype=np.uint32).tobytes()),
                    componentType=pygltflib.UNSIGNED_INT),
                values=pygltflib.AccessorSparseValues(bufferView=self.view(values.tobytes())))
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def mesh(self, name: str, vertices, faces, color, colors=None, targets=(), uv=None, image: int | None = None,
             normals: np.ndarray | None = None) -> int:
        """A mesh node (index) of one surface; uv (n, 2) and image (a glTF image index): its
        base colour texture; normals (n, 3) to use instead of the mesh's own."""
        vertices = np.asarray(vertices, dtype=np.float64)
        normals = vertex_normals(vertices, faces) if normals is None else normals
        attributes = pygltflib.Attributes(
            POSITION=self.accessor(vertices.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3, _ARRAY_BUFFER, True),
            NORMAL=self.accessor(np.asarray(normals, dtype=np.float32), pygltflib.FLOAT, pygltflib.VEC3,
                                 _ARRAY_BUFFER))
        if colors is not None:
            c = np.asarray(colors, dtype=np.float32)
            c = np.clip(np.concatenate([c[:, :3], c[:, 3:4] if c.shape[1] > 3 else np.ones((len(c), 1), np.float32)],
                                       axis=1), 0.0, 1.0)
            attributes.COLOR_0 = self.accessor(c, pygltflib.FLOAT, pygltflib.VEC4, _ARRAY_BUFFER)
        indices = self.accessor(np.asarray(faces).astype(np.uint32).reshape(-1), pygltflib.UNSIGNED_INT,
                                pygltflib.SCALAR, _ELEMENT_ARRAY_BUFFER)
        base = [1.0, 1.0, 1.0, 1.0] if colors is not None else [min(max(float(c), 0.0), 1.0) for c in color]
        texture = None
        if uv is not None and image is not None:
            attributes.TEXCOORD_0 = self.accessor(np.asarray(uv, dtype=np.float32), pygltflib.FLOAT, pygltflib.VEC2,
                                                  _ARRAY_BUFFER)
            texture = wrapped_texture(self.gltf, image)
            base = [1.0, 1.0, 1.0, 1.0]
        self.gltf.materials.append(pygltflib.Material(
            name=name, pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorFactor=base, metallicFactor=0.0, roughnessFactor=ROUGHNESS.get(name, DEFAULT_ROUGHNESS),
                baseColorTexture=texture),
            alphaMode=pygltflib.BLEND if base[3] < 1.0 else None))
        primitive = pygltflib.Primitive(attributes=attributes, indices=indices, material=len(self.gltf.materials) - 1,
                                        mode=pygltflib.TRIANGLES)
        mesh = pygltflib.Mesh(name=name, primitives=[primitive])
        if targets:
            primitive.targets = [pygltflib.Attributes(POSITION=self.sparse_target(len(vertices), t.vertices,
                                                                                   t.displacement)) for t in targets]
            mesh.weights = [0.0] * len(targets)
            mesh.extras = {"targetNames": [t.name for t in targets]}
        self.gltf.meshes.append(mesh)
        self.gltf.nodes.append(pygltflib.Node(name=name, mesh=len(self.gltf.meshes) - 1))
        return len(self.gltf.nodes) - 1

    def glb(self) -> bytes:
        m, g = self.model, self.gltf
        bones = {b: len(g.nodes) + i for i, b in enumerate(BONE_PARENTS)}
        for b in BONE_PARENTS:
            g.nodes.append(pygltflib.Node(name=f"{b}_bone"))
        children = {b: [] for b in BONE_PARENTS}
        for b, parent in BONE_PARENTS.items():
            if parent is not None:
                children[parent].append(bones[b])
        colors = None if self.skin_colors is None else np.asarray(self.skin_colors, dtype=np.float32)
        if getattr(m, "skin_texture", None) is None:
            skin = self.mesh("skin", m.skin_vertices, m.skin_faces, np.asarray(m.skin_color, dtype=np.float32),
                             colors=colors, targets=self.targets)
        else:
            skin = self.textured_skin(colors)
        children["head"].insert(0, skin)
        for part_name, part in m.parts.items():
            if part_name in HIDDEN_PARTS or len(part.faces) == 0 or part.bone not in children:
                continue
            children[part.bone].append(self.mesh(part_name, part.vertices, part.faces, part.color,
                                                 colors=part.vertex_colors))
        for b, kids in children.items():
            g.nodes[bones[b]].children = kids
        if self.keyframes is not None and len(self.keyframes.times):
            self.animation(skin, bones)
        g.asset = pygltflib.Asset(version="2.0", generator=GENERATOR)
        g.scenes = [pygltflib.Scene(name=str(self.name), nodes=[bones["head"]])]
        g.scene = 0
        self.blob += b"\0" * (-len(self.blob) % _ALIGNMENT)
        g.buffers = [pygltflib.Buffer(byteLength=len(self.blob))]
        g.set_binary_blob(bytes(self.blob))
        return b"".join(g.save_to_bytes())

    def textured_skin(self, colors: np.ndarray | None) -> int:
        """The skin's mesh node with its texture: the vertices of the triangles that cross the
        texture's seam are repeated (fae.mesh.wrapped_seam), in the mesh and in every morph
        target; vertex colours, when given, become factors of the texture (1 where they are
        the skin colour, darker inside the mouth)."""
        m = self.model
        n = len(m.skin_vertices)
        V2, F2, uv2, N2, source = seamed_surface(m.skin_vertices, m.skin_faces, m.skin_uv)
        targets = []
        for t in self.targets:
            row = np.full(n, -1, dtype=np.int64)
            row[np.asarray(t.vertices, dtype=np.int64)] = np.arange(len(t.vertices))
            copies = np.flatnonzero(row[source] >= 0)
            targets.append(_Target(t.name, np.concatenate([t.vertices, n + copies]),
                                   np.concatenate([t.displacement, np.asarray(t.displacement)[row[source[copies]]]])))
        factors = None
        if colors is not None:
            factors = texture_factors(colors, m.skin_color)
            factors = np.concatenate([factors, factors[source]])
        image = len(self.gltf.images)
        self.gltf.images.append(pygltflib.Image(bufferView=self.view(png_bytes(m.skin_texture)), mimeType="image/png"))
        return self.mesh("skin", V2, F2, np.asarray(m.skin_color, dtype=np.float32),
                         colors=factors, targets=targets, uv=uv2, image=image, normals=N2)

    def animation(self, skin: int, bones: dict[str, int]) -> None:
        k = self.keyframes
        times = np.asarray(k.times, dtype=np.float32)
        if len(times) > 1 and np.any(np.diff(times) <= 0):
            raise ValueError("keyframes.times: expected strictly increasing seconds")
        time_input = self.accessor(times, pygltflib.FLOAT, pygltflib.SCALAR, bounds=True)
        samplers, channels = [], []

        def channel(node: int, path: str, values: np.ndarray, kind: str) -> None:
            output = self.accessor(np.asarray(values, dtype=np.float32), pygltflib.FLOAT, kind)
            samplers.append(pygltflib.AnimationSampler(input=time_input, output=output, interpolation="LINEAR"))
            channels.append(pygltflib.AnimationChannel(sampler=len(samplers) - 1,
                                                       target=pygltflib.AnimationChannelTarget(node=node, path=path)))

        if self.targets:
            weights = np.asarray(k.weights, dtype=np.float32).reshape(len(times), len(self.targets))
            channel(skin, "weights", weights.reshape(-1), pygltflib.SCALAR)
        for b, local in local_transforms(k.bone_transforms).items():
            translation, rotation, scale = decompose(local)
            channel(bones[b], "translation", translation, pygltflib.VEC3)
            channel(bones[b], "rotation", rotation, pygltflib.VEC4)
            if np.abs(scale - 1.0).max() > 1e-6:
                channel(bones[b], "scale", scale, pygltflib.VEC3)
        self.gltf.animations = [pygltflib.Animation(name=str(self.name), samplers=samplers, channels=channels)]
