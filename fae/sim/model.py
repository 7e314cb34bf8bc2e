"""SkinModel, State and Control: the static arrays, the changing state and the inputs of the skin.

Reads like Warp's simulators: a `SkinModel` holds what never changes while a head plays
(rest positions, masses, springs, holds and anchors, muscle influences, bone distance grids),
a `State` what does (particle positions and velocities), a `Control` the inputs of one
step (muscle activations, bone poses). A solver maps ``(model, state_in, control, dt)`` to
``state_out``. Arrays are named ``<thing>_<attr>``, counts ``<thing>_count``.

Everything here lives in the head's own frame (metres, +y up, +z forward, +x the face's
left). Bones: index 0 is "head" (cranium, upper teeth), index 1 is "jaw" (mandible, lower
teeth); a bone pose maps rest positions to current positions, x' = R x + t.

Muscles are the face model's Waters muscles plus directional pull fields (kind 2): a
pull field pushes its particles along a fixed direction of the head frame, weighted by a
radial fall-off around a feature point; the runtime uses them for motions no muscle makes
(eyelids, nostrils, lip protrusion), see :mod:`fae.animate.calibrate`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
import warp as wp

BONE_NAMES = ("head", "jaw")
BONE_COUNT = len(BONE_NAMES)
# A Control's poses: the bones' now, then where they were at the step's start (the holds
# move from those to these over the step, and the skin's drag is taken relative to them)
POSE_COUNT = 2 * BONE_COUNT

MUSCLE_LINEAR = 0
MUSCLE_SPHINCTER = 1
MUSCLE_FIELD = 2

LAYER_COUNT = 3

_lazy_arrays_lock = threading.Lock()


@dataclass
class SkinModel:
    """Static arrays of the 3-layer mass-spring-damper skin (Warp arrays on `device`).

    Particles are the simulated subset of the three layers (see `particle_layer`); skin
    vertices far from every muscle are not simulated (`skin_particle` is -1 for them) and
    are carried by their hold (`skin_jaw`, fae.sim.build.skin_positions).

    particle_q          (P,) vec3  metres, rest positions
    particle_mass       (P,) float kg
    particle_inv_mass   (P,) float 1/kg; 0 for particles held fixed (the border ring)
    particle_layer      (P,) int   0 epidermis, 1 middle, 2 deepest
    particle_collider   (P,) int   1 for particles that must stay outside the bones, else 0
    particle_clearance  (P,) vec2  metres, per bone: no closer to its rest place in the bone's
                                   frame than this, the particle cannot be inside the bone
    particle_sphere     (P,) vec4  an eyeball the particle stays outside of: centre (metres,
                                   the skull's rest frame) and radius (metres, the eyeball's
                                   plus the particle's clearance); radius 0: no minimum (the
                                   centre still serves particle_sphere_max)
    particle_sphere_max (P,) float metres, the farthest from that eyeball's centre the particle
                                   may go (skin hidden behind the lids: the lining stays
                                   behind the lid's front); 0: no limit
    particle_drag       (P,) float 1/s: velocity drag applied implicitly each substep (`damping`,
                                   less where a pull field asks for a quicker skin)
    particle_carried_drag (P,) float 1/s: the part of particle_drag that resists motion
                        relative to the particle's hold as the bones move it (fae.sim.integrate)
    contact_depth       metres: deeper penetrations are left to the springs (fae.sim.collision)
    triangle_count      triangles of the two upper layers guarded against folding (fae.sim.folds)
    triangle_guard      (T,) fae.sim.folds.GuardedTriangle: particles, rest shape, rest normal
    fold_min_area       a guarded triangle below this fraction of its rest area is restored
    fold_passes         guard passes per substep
    crease_vertex       (P0,) fae.sim.folds.CreaseVertex, P0 the epidermis particles (the first
                                   P0): neighbours and rest offset from their mean (none for
                                   fixed ones)
    crease_neighbours   (N,) int   the neighbour lists
    crease_rest_length  (N,) float metres, rest length of each neighbour's edge; 0: its strain
                                   is not limited
    crease_tolerance    a particle whose offset strays more than this x its mean rest edge is
                                   moved back (fae.sim.folds.smooth_creases)
    strain_max, strain_min  an epidermis edge is kept within these x its rest length
    lip_pair_count      pairs of upper- and lower-lip particles kept in order (lip contact;
                        and of each upper lid's lining over its front's margin, and of each
                        upper lid's skin over the lower lid's margin: fae.sim.folds.lid_pairs)
    lip_pair            (K,) fae.sim.folds.LipPair
    spring_indices      (S*2,) int particle pairs
    spring_rest_length  (S,) float metres
    spring_stiffness    (S,) float N/m
    particle_jaw        (P,) float in [0, 1]: how much the particle's hold follows the jaw; the
                                   hold is (1 - w) x (head pose of rest) + w x (jaw pose of rest)
    particle_anchor_stiffness (P,) float N/m, zero-length spring to the hold (deepest layer
                                   stiffly, the others weakly; 0 for fixed particles, which
                                   sit on their hold)
    muscle_kind         (M,) int   MUSCLE_LINEAR / MUSCLE_SPHINCTER / MUSCLE_FIELD
    muscle_bone         (M,) int   bone carrying a linear muscle's attachment (else 0)
    muscle_point        (M,) vec3  metres: linear attachment at rest; sphincter centre
    muscle_axis_u       (M,) vec3  sphincter horizontal axis; field direction
    muscle_axis_v       (M,) vec3  sphincter vertical axis
    muscle_scale        (M,) float metres: sphincter's larger semi-axis (else 1)
    particle_below      (P,) int   an epidermis particle's vertex in the middle layer, or -1
    particle_normal     (P,) vec3  unit, rest direction from that particle to this one
    particle_height     (P,) float metres, the least height above it (`layer_min_height` x rest)
    row_influence_start (P+1,) int the influences of particle i are start[i]:start[i+1]
    influence_muscle    (I,) int   one entry per (muscle, particle) with non-zero weight,
                                   sorted by particle
    influence_particle  (I,) int
    influence_weight    (I,) float N per unit activation (weight x particle mass x
                                   `muscle_acceleration`)
    sdf_values          (BONE_COUNT,) wp.array3d float metres, signed distance to the
                                   bone's meshes in its own rest frame (< 0 inside)
    sdf_origin          (BONE_COUNT, 3) numpy float64 metres, grid corner
    sdf_spacing         (BONE_COUNT,) numpy float64 metres, cell size
    skin_particle       (V,) numpy int, epidermis particle of each skin vertex or -1
    skin_jaw            (V,) numpy float, jaw weight of each skin vertex's hold
    skin_rest           (V, 3) numpy float64 metres, skin at rest
    dt_max              seconds: the largest stable substep (see solver)
    damping             1/s: the skin's velocity drag (particle_drag where no field lowers it)
    """

    device: str
    particle_count: int
    particle_q: wp.array
    particle_mass: wp.array
    particle_inv_mass: wp.array
    particle_layer: wp.array
    particle_collider: wp.array
    particle_clearance: wp.array
    particle_sphere: wp.array
    particle_sphere_max: wp.array
    particle_drag: wp.array
    particle_carried_drag: wp.array
    spring_count: int
    spring_indices: wp.array
    spring_rest_length: wp.array
    spring_stiffness: wp.array
    particle_jaw: wp.array
    particle_anchor_stiffness: wp.array
    muscle_count: int
    muscle_names: list[str]
    muscle_kind: wp.array
    muscle_bone: wp.array
    muscle_point: wp.array
    muscle_axis_u: wp.array
    muscle_axis_v: wp.array
    muscle_scale: wp.array
    row_influence_start: wp.array
    particle_below: wp.array
    particle_normal: wp.array
    particle_height: wp.array
    influence_count: int
    influence_muscle: wp.array
    influence_particle: wp.array
    influence_weight: wp.array
    contact_depth: float
    triangle_count: int
    triangle_guard: wp.array
    fold_min_area: float
    fold_passes: int
    crease_vertex: wp.array
    crease_neighbours: wp.array
    crease_rest_length: wp.array
    crease_tolerance: float
    strain_max: float
    strain_min: float
    lip_pair_count: int
    lip_pair: wp.array
    sdf_values: list
    sdf_origin: np.ndarray
    sdf_spacing: np.ndarray
    skin_particle: np.ndarray
    skin_jaw: np.ndarray
    skin_rest: np.ndarray
    dt_max: float
    damping: float
    jaw_pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))
    jaw_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    # arrays made from the ones above when first needed (not copied by dataclasses.replace)
    _skin_arrays: tuple | None = field(default=None, init=False, repr=False, compare=False)
    _packed: tuple | None = field(default=None, init=False, repr=False, compare=False)  # fae.sim.solver.packed_arrays
    _triangles_of: tuple | None = field(default=None, init=False, repr=False, compare=False)  # fae.sim.solver
    # what a part of the face shares with the whole (fae.sim.build.skin_model's `like`)
    _face_setup: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def state(self) -> "State":
        """A State at rest, on the model's device."""
        q = wp.clone(self.particle_q)
        qd = wp.zeros(self.particle_count, dtype=wp.vec3, device=self.device)
        return State(particle_q=q, particle_qd=qd)

    def control(self) -> "Control":
        """A Control at rest: no activation, bones at their rest pose."""
        return Control(
            muscle_activation=wp.zeros(self.muscle_count, dtype=wp.float32, device=self.device),
            bone_rotation=wp.array(np.tile(np.eye(3, dtype=np.float32), (POSE_COUNT, 1, 1)), dtype=wp.mat33, device=self.device),
            bone_translation=wp.zeros(POSE_COUNT, dtype=wp.vec3, device=self.device),
        )

    def skin_arrays(self) -> tuple[wp.array, wp.array, wp.array]:
        """(skin_particle (V,) int, skin_rest (V,) vec3, skin_jaw (V,) float) as Warp arrays on
        the model's device, made once and shared by everything that draws this model's skin."""
        return self.made_once("_skin_arrays", lambda m: (
            wp.array(m.skin_particle.astype(np.int32), dtype=int, device=m.device),
            wp.array(m.skin_rest.astype(np.float32), dtype=wp.vec3, device=m.device),
            wp.array(m.skin_jaw.astype(np.float32), dtype=float, device=m.device)))

    def made_once(self, name: str, make):
        """The model's attribute `name`, made by make(model) when it is first asked for (under
        a lock: a server's faces may ask at once), from the arrays as they are then."""
        value = getattr(self, name)
        if value is None:
            with _lazy_arrays_lock:
                value = getattr(self, name)
                if value is None:
                    value = make(self)
                    setattr(self, name, value)
        return value

    def numpy_arrays(self) -> dict[str, np.ndarray]:
        """All Warp arrays of the model as numpy arrays (for the reference step and tests)."""
        out = {}
        for name, value in vars(self).items():
            if isinstance(value, wp.array):
                out[name] = value.numpy()
        out["sdf_values"] = [None if v is None else v.numpy() for v in self.sdf_values]
        return out


@dataclass
class State:
    """particle_q (P,) vec3 metres; particle_qd (P,) vec3 metres/s."""

    particle_q: wp.array
    particle_qd: wp.array

    def assign(self, other: "State") -> None:
        wp.copy(self.particle_q, other.particle_q)
        wp.copy(self.particle_qd, other.particle_qd)


@dataclass
class Control:
    """Inputs of a step.

    muscle_activation (M,) float, dimensionless (muscle force = activation x weight)
    bone_rotation     (POSE_COUNT,) mat33, rest -> now for each bone, then rest -> the
                      step's start (the bones move between the two over the next step)
    bone_translation  (POSE_COUNT,) vec3 metres, likewise
    """

    muscle_activation: wp.array
    bone_rotation: wp.array
    bone_translation: wp.array
    _views: dict = field(default_factory=dict, repr=False, compare=False)  # numpy views of CPU arrays

    def set(self, muscle_activation: np.ndarray | None = None, bone_rotation: np.ndarray | None = None,
            bone_translation: np.ndarray | None = None, moving: bool = False) -> None:
        """Copy numpy values in: (M,), bone poses (BONE_COUNT, 3, 3) and (BONE_COUNT, 3) (or
        the same values flat). The bones are placed there (no motion in the next step), or,
        `moving`, move there over the next step from the poses this control held: the
        skin's holds go with them and part of its drag resists only what moves relative to
        its hold. A moving control describes one step: a player sets it, steps once, and
        sets it again (stepped twice, the motion plays twice). A pose not given stays where
        it is, unmoving. Placed bones may also be given as all POSE_COUNT poses."""
        for array, value in ((self.muscle_activation, muscle_activation),
                             (self.bone_rotation, self._poses(self.bone_rotation, bone_rotation, moving)),
                             (self.bone_translation, self._poses(self.bone_translation, bone_translation, moving))):
            if array.device.is_cpu:
                # the array's own memory: no temporary Warp array per frame
                view = self._views.get(id(array))
                if view is None:
                    view = self._views[id(array)] = array.numpy()
                if value is not None:
                    np.copyto(view, np.reshape(value, view.shape), casting="unsafe")
            elif value is not None:
                array.assign(np.asarray(value, dtype=np.float32))

    def _poses(self, array: wp.array, now: np.ndarray | None, moving: bool) -> np.ndarray:
        """(POSE_COUNT, ...) values for a pose array: the poses `now` (BONE_COUNT, ...; None:
        the ones it holds) at the step's end, then at its start what it held (`moving`) or
        `now` again."""
        view = self._views.get(id(array))
        held = (view if view is not None else array.numpy())[:BONE_COUNT].astype(np.float64)  # a copy
        if now is None:
            return np.concatenate([held, held])
        now = np.asarray(now, dtype=np.float64)
        if now.size == 2 * held.size and not moving:  # every pose given
            return now.reshape((POSE_COUNT,) + held.shape[1:])
        if now.size != held.size:
            raise ValueError(f"bone poses: expected {held.size} values ({BONE_COUNT} bones"
                             f"{'' if moving else f', or {2 * held.size} for all {POSE_COUNT} poses placed'}), "
                             f"got shape {now.shape}")
        now = now.reshape(held.shape)
        return np.concatenate([now, held if moving else now])
