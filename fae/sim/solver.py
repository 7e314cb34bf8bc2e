"""The skin solver: symplectic Euler with implicit drag and anchors, contact projection.

Scheme. A frame of length dt is split into n = ceil(dt / dt_max) equal substeps h; each is

    f = springs (a scatter over rows of springs, fae.sim.springs);
    one pass over particles (fae.sim.integrate): f += muscles;
        v' = (v + h/m (f + k_a (hold - x)) + h c_a u) / (1 + h c + h^2 (k_a + k_m) / m);  x' = x + h v'
        (the hold moving with the bones over the frame at velocity u, c_a the part of the
        drag carried with it);
        upper layers kept above the next; contact with skull and mandible (fae.sim.collision);
    then up to `fold_passes` passes of the fold guard, crease smoothing and lip contact
    (fae.sim.folds), each move stopping at the bones.

Stability. The drag c (1/s, per particle: lower where a pull field asks, fae.sim.build),
each particle's anchor k_a (a zero-length spring to its hold)
and the stiffness k_m of the muscles contracted on it are implicit, the springs explicit.
For one mode of the springs of frequency w (w^2 an eigenvalue of M^-1 K_s) on a particle
with anchor rate kappa_a = k_a / m, the step's amplification matrix has determinant
1 / (1 + h c + h^2 kappa_a) < 1 and its eigenvalues stay inside the unit circle while

    h^2 w^2 < 4 + 2 h c + h^2 kappa_a.

The drag therefore buys a much longer step than the undamped bound h w < 2, and the
anchors (the stiffest part of the skin, kappa_anchor 10000 1/s^2) and muscles (a sphincter
at its activation limit is stiffer than all the springs) cost none. `dt_max` is the largest
h that satisfies this for the springs' largest w^2 (Lanczos over the spring network's
weighted graph Laplacian, which bounds M^-1 K_s in every configuration without compressed
springs, see fae.sim.build) and the weakest anchor, with a safety factor cfl = 0.9 on w;
where a pull field lowers the drag (the eyelids'), the same bound over that skin's own
rows of the network with its lowest drag.
On the shipped head dt_max is 20 ms: two substeps per 25 or 30 fps frame, one at 50 fps
and up (8.4 ms, five substeps per 25 fps frame, with the same springs twice as stiff and
drag and anchors explicit).

Contact is a position projection (no stiff penalty springs): a step that reached a bone
ends on its surface, skin the bone moved onto is pushed out on the side it belongs to
(fae.sim.collision). Kernels are compiled with fast math.

The kernels read each spring's and each particle's constants as one record
(`packed_arrays`). Per substep the solver replays two recorded launches (Warp's `record_cmd`), made once per
(states, control): a plain `wp.launch` packs its 27 arguments anew each time, which cost
as much as the springs themselves. (Warp's graph capture would replay a whole frame in one
call, but on the CPU it records every Warp call of the process while it captures, so a
second face being built in another thread, as `fae serve` does, breaks it.)

Schemes not taken: a per-particle gather of the springs (no atomics) measured 1.5x slower
on the CPU than the scatter, since it evaluates each spring from both ends; a prefactored
implicit (projective dynamics) step needs a sparse triangular solve of about 2 million
non-zeros for the full three-layer skin of the shipped head (21,840 particles), 7.5 ms per
frame in C on one core, more than the whole explicit frame.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

import fae.sim.folds as _folds
import fae.sim.integrate as _integrate
import fae.sim.muscles as _muscles
import fae.sim.springs as _springs
from fae.sim.launch import LaunchCache, call_first_alone
from fae.sim.model import Control, SkinModel, State

# consecutive springs / particles per Warp thread on the CPU (see fae.sim.springs)
CPU_SPRING_CHUNK = 16  # rows of springs (about seven springs each on the shipped head)
CPU_PARTICLE_CHUNK = 64


def substep_count(model: SkinModel, dt: float) -> int:
    """Number of stable substeps for a step of dt seconds."""
    if not (dt > 0.0) or not math.isfinite(dt):
        raise ValueError(f"step: dt must be a positive number of seconds, got {dt!r}")
    return max(1, int(math.ceil(dt / model.dt_max - 1e-9)))


def stable_substep(spring_rate: float, anchor_rate: float, damping: float, cfl: float = 0.9) -> float:
    """Seconds: the largest h with (cfl w)^2 ... see module docstring:
    h^2 w^2 <= cfl^2 (4 + 2 h c + h^2 kappa_a), w^2 = `spring_rate` (1/s^2), kappa_a =
    `anchor_rate` (1/s^2, the weakest anchor), c = `damping` (1/s). At most 1 s."""
    a = float(spring_rate) - cfl * cfl * float(anchor_rate)
    b = cfl * cfl * float(damping)
    if a <= 0.0:
        return 1.0
    return min(1.0, (b + math.sqrt(b * b + 4.0 * cfl * cfl * a)) / a)


def packed_arrays(model: SkinModel) -> tuple[wp.array, wp.array, wp.array]:
    """(particle_spring_start (P+1,) int, springs (S,) fae.sim.springs.Spring, particle_static
    (P,) fae.sim.integrate.ParticleStatic): the model's springs in rows (the springs of
    particle i to higher-numbered ones are springs[start[i]:start[i + 1]]) and its particle
    constants as one record each, on its device; made once per model (SkinModel.made_once)
    and shared by all its solvers: a model is not to be changed after its first solver."""
    return model.made_once("_packed", _pack)


def _pack(model: SkinModel) -> tuple[wp.array, wp.array, wp.array]:
    """The arrays of `packed_arrays`, made now."""
    pairs = model.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
    low, high = pairs.min(axis=1), pairs.max(axis=1)
    order = np.lexsort((high, low))
    springs = np.zeros(model.spring_count, dtype=_springs.Spring.numpy_dtype())
    springs["j"] = high[order]
    springs["rest_length"] = model.spring_rest_length.numpy()[order]
    springs["stiffness"] = model.spring_stiffness.numpy()[order]
    spring_start = np.concatenate([[0], np.cumsum(np.bincount(low, minlength=model.particle_count))])
    static = np.zeros(model.particle_count, dtype=_integrate.ParticleStatic.numpy_dtype())
    start = model.row_influence_start.numpy()
    for name, values in (("rest", model.particle_q), ("jaw", model.particle_jaw),
                         ("inv_mass", model.particle_inv_mass), ("anchor_stiffness", model.particle_anchor_stiffness),
                         ("below", model.particle_below), ("normal", model.particle_normal),
                         ("height", model.particle_height), ("collider", model.particle_collider),
                         ("clearance", model.particle_clearance), ("sphere", model.particle_sphere),
                         ("sphere_max", model.particle_sphere_max), ("drag", model.particle_drag),
                         ("carried_drag", model.particle_carried_drag)):
        static[name] = values.numpy()
    static["influence_first"], static["influence_end"] = start[:-1], start[1:]
    return (wp.array(spring_start.astype(np.int32), dtype=int, device=model.device),
            wp.array(springs, dtype=_springs.Spring, device=model.device),
            wp.array(static, dtype=_integrate.ParticleStatic, device=model.device))


def triangles_of_particles(model: SkinModel) -> tuple[wp.array, wp.array]:
    """(start (P+1,) int, triangles (3T,) int): the guarded triangles of particle p are
    triangles[start[p]:start[p + 1]] (fae.sim.folds.guard_folds_near); made once per model
    and shared by its solvers, as packed_arrays."""
    return model.made_once("_triangles_of", _make_triangles_of)


def _make_triangles_of(model: SkinModel) -> tuple[wp.array, wp.array]:
    """The arrays of `triangles_of_particles`, made now."""
    P = model.particle_count
    if not model.triangle_count:
        return wp.zeros(P + 1, dtype=int, device=model.device), wp.zeros(1, dtype=int, device=model.device)
    tri = model.triangle_guard.numpy()
    corners = np.concatenate([tri["i"], tri["j"], tri["k"]]).astype(np.int64)
    owner = np.tile(np.arange(len(tri)), 3)
    order = np.argsort(corners, kind="stable")
    start = np.concatenate([[0], np.cumsum(np.bincount(corners, minlength=P))])
    return (wp.array(start.astype(np.int32), dtype=int, device=model.device),
            wp.array(owner[order].astype(np.int32), dtype=int, device=model.device))


class SkinSolver:
    """Advances a SkinModel's State under a Control; allocates its scratch arrays once."""

    def __init__(self, model: SkinModel):
        self.model = model
        cpu = wp.get_device(model.device).is_cpu
        self.spring_chunk = CPU_SPRING_CHUNK if cpu else 1
        self.particle_chunk = CPU_PARTICLE_CHUNK if cpu else 1
        self.particle_f = wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
        # the fold guard's moves, cleared by the pass that applies them (fae.sim.folds)
        self.particle_move = wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
        self.particle_moves = wp.zeros(model.particle_count, dtype=float, device=model.device)
        self.particle_crease = wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
        # [moves asked (triangles, creases, strained edges, lip pairs), particles on `touched`]
        # in the current pass
        self.pass_counts = wp.zeros(2, dtype=int, device=model.device)
        # [the share of the step done at the current substep's end, one substep's share]:
        # the holds move with the bones over a step (fae.sim.integrate)
        self.step_phase = wp.zeros(2, dtype=float, device=model.device)
        self._step_phase = self.step_phase.numpy() if cpu else None
        self.touched = wp.zeros(model.particle_count, dtype=int, device=model.device)
        # the particles the last pass moved: flagged, and listed in one of two lists (the
        # next pass reads one while its moves fill the other), `_moved_list` the current one
        self.particle_moved = wp.zeros(model.particle_count, dtype=int, device=model.device)
        self.moved = [wp.zeros(model.particle_count, dtype=int, device=model.device) for _ in range(2)]
        self.moved_counts = wp.zeros(2, dtype=int, device=model.device)
        self._moved_list = 0
        self.triangle_start, self.particle_triangles = triangles_of_particles(model)
        self._cpu = cpu
        self._scratch = (model.state(), model.state())
        no_grid = wp.full((2, 2, 2), 1.0, dtype=float, device=model.device)  # far outside everywhere
        self._grids = []
        for b in range(2):
            values = model.sdf_values[b] if b < len(model.sdf_values) else None
            o = model.sdf_origin[b] if values is not None else np.zeros(3)
            self._grids += [no_grid if values is None else values, wp.vec3(*(float(c) for c in o)),
                            float(model.sdf_spacing[b]) if values is not None else 1.0]
        self._launches = LaunchCache()
        # the muscles' points and axes carried by their bones, once per step
        self._muscle_point = wp.zeros(max(model.muscle_count, 1), dtype=wp.vec3, device=model.device)
        self._muscle_axis_u = wp.zeros_like(self._muscle_point)
        self._muscle_axis_v = wp.zeros_like(self._muscle_point)
        self._pose_launches = LaunchCache()
        # (a model without muscles or springs skips their kernels: its first step runs fewer)
        call_first_alone(("SkinSolver", str(wp.get_device(model.device)), model.muscle_count > 0, model.spring_count > 0),
                         self._first_step)

    def _first_step(self) -> None:
        """One step at rest, to run every kernel once (see `call_first_alone`)."""
        state = self.model.state()
        self.step(self.model, state, self.model.control(), self.model.dt_max, state)
        self._launches, self._pose_launches = LaunchCache(), LaunchCache()

    def _pose_muscles(self, control: Control) -> None:
        m = self.model
        if m.muscle_count == 0:
            return
        self._pose_launches.get((control,), lambda: wp.launch(
            _muscles.pose_muscles, dim=m.muscle_count, device=m.device, record_cmd=True,
            inputs=[m.muscle_bone, m.muscle_point, m.muscle_axis_u, m.muscle_axis_v,
                    control.bone_rotation, control.bone_translation],
            outputs=[self._muscle_point, self._muscle_axis_u, self._muscle_axis_v])).launch()

    def _substep_launches(self, src: State, dst: State, control: Control, h: float) -> list:
        """[springs, particles, guard, apply guard, h] recorded launches from src to dst, their
        step set to h: guard (the first pass's launches, [the later passes' launches] per moved
        list read), apply guard [(forget_moved, apply_guard)] per moved list read; both None
        for a model without guarded triangles."""
        def record() -> list:
            m = self.model
            spring_start, spring_records, particle_static = packed_arrays(m)
            springs = wp.launch(_springs.eval_springs, dim=-(-m.particle_count // self.spring_chunk), device=m.device,
                                inputs=[src.particle_q, spring_start, spring_records, m.particle_count,
                                        self.spring_chunk],
                                outputs=[self.particle_f], record_cmd=True)
            particles = wp.launch(
                _integrate.step_particles, dim=-(-m.particle_count // self.particle_chunk), device=m.device,
                inputs=[src.particle_q, src.particle_qd, self.particle_f, particle_static,
                        m.influence_muscle, m.influence_weight,
                        m.muscle_kind, self._muscle_point, self._muscle_axis_u, self._muscle_axis_v,
                        m.muscle_scale, control.muscle_activation, control.bone_rotation,
                        control.bone_translation, *self._grids, float(m.contact_depth),
                        float(h), self.step_phase, m.particle_count, self.particle_chunk],
                outputs=[dst.particle_q, dst.particle_qd], record_cmd=True)
            guard = apply = None
            if m.triangle_count:
                chunks = -(-m.particle_count // self.particle_chunk)
                rotation, chunk, counts = control.bone_rotation, self.particle_chunk, self.pass_counts
                moves = [self.particle_move, self.particle_moves, self.touched, counts]
                # a substep's first pass looks at every triangle and particle, a later one (per
                # list it reads) only next to what the pass before it moved
                first = [wp.launch(_folds.guard_folds, dim=-(-m.triangle_count // chunk), device=m.device,
                                   inputs=[dst.particle_q, m.triangle_guard, rotation, float(m.fold_min_area),
                                           m.triangle_count, chunk], outputs=moves, record_cmd=True)]
                later = [[wp.launch(_folds.guard_folds_near, dim=chunks, device=m.device,
                                    inputs=[dst.particle_q, m.triangle_guard, rotation, float(m.fold_min_area), chunk,
                                            self.moved[which], self.moved_counts, which, self.particle_moved,
                                            self.triangle_start, self.particle_triangles],
                                    outputs=moves, record_cmd=True)] for which in (0, 1)]
                n_crease = len(m.crease_vertex)
                crease_args = [dst.particle_q, m.crease_vertex, m.crease_neighbours, m.crease_rest_length, rotation,
                               float(m.crease_tolerance), float(m.strain_max), float(m.strain_min), n_crease, chunk]
                first.append(wp.launch(_folds.smooth_creases, dim=-(-n_crease // chunk), device=m.device,
                                       inputs=crease_args, outputs=[*moves, self.particle_crease], record_cmd=True))
                for which in (0, 1):
                    later[which].append(wp.launch(
                        _folds.smooth_creases_near, dim=chunks, device=m.device,
                        inputs=[*crease_args, self.moved[which], self.moved_counts, which, self.particle_moved],
                        outputs=[*moves, self.particle_crease], record_cmd=True))
                if m.lip_pair_count:
                    lips = wp.launch(_folds.separate_lips, dim=m.lip_pair_count, device=m.device,
                                     inputs=[dst.particle_q, m.lip_pair, rotation, m.lip_pair_count],
                                     outputs=moves, record_cmd=True)
                    for launches in (first, *later):
                        launches.append(lips)
                guard = (first, later)
                apply = [(wp.launch(_folds.forget_moved, dim=chunks, device=m.device,
                                    inputs=[self.moved[which], self.moved_counts, which, chunk],
                                    outputs=[self.particle_moved], record_cmd=True),
                          wp.launch(_folds.apply_guard, dim=chunks, device=m.device,
                                    inputs=[particle_static, self.particle_move, self.particle_moves,
                                            self.particle_crease, rotation, control.bone_translation, *self._grids,
                                            float(m.contact_depth), self.touched, counts, chunk, which],
                                    outputs=[dst.particle_q, dst.particle_qd, self.particle_moved,
                                             self.moved[1 - which], self.moved_counts], record_cmd=True))
                         for which in (0, 1)]
            return [springs, particles, guard, apply, h]

        entry = self._launches.get((src, dst, control), record)
        if entry[4] != h:
            entry[1].set_param_by_name("dt", float(h))
            entry[4] = h
        return entry

    def _guard(self, model: SkinModel, first: list, later: list, apply: list) -> None:
        """The fold guard's passes over one substep's result (fae.sim.folds)."""
        for pass_index in range(model.fold_passes):
            self.pass_counts.zero_()
            which = self._moved_list
            for launch in first if pass_index == 0 else later[which]:
                launch.launch()
            if self._cpu and self.pass_counts.numpy()[0] == 0:
                break  # nothing near folding (on CUDA, reading this would stall the queue)
            for launch in apply[which]:
                launch.launch()
            self._moved_list = 1 - which

    def _forget_guard(self) -> None:
        """The guard's moves, flags and lists cleared (its kernels keep them consistent only
        from pass to pass)."""
        for a in (self.particle_move, self.particle_moves, self.particle_crease, self.particle_moved,
                  self.moved_counts, self.pass_counts):
            a.zero_()
        self._moved_list = 0

    def step(self, model: SkinModel, state_in: State, control: Control, dt: float,
             state_out: State | None = None) -> State:
        """Advance dt seconds (split into stable substeps); returns state_out (new if None).

        state_in is left unchanged unless it is also state_out.
        """
        if model is not self.model:
            raise ValueError("step: this solver was built for another SkinModel")
        if state_out is None:
            state_out = model.state()
        n = substep_count(model, dt)
        h = dt / n
        self._pose_muscles(control)
        src = state_in
        for k in range(n):
            dst = state_out if k == n - 1 and state_out is not src else self._scratch[k % 2]
            if dst is src:
                dst = self._scratch[(k + 1) % 2]
            springs, particles, guard, apply = self._substep_launches(src, dst, control, h)[:4]
            phase = ((k + 1) / n, 1.0 / n)
            if self._step_phase is not None:
                self._step_phase[:] = phase
            else:
                self.step_phase.assign(np.array(phase, dtype=np.float32))
            self.particle_f.zero_()
            if model.spring_count:
                springs.launch()
            particles.launch()
            if guard is not None:
                try:
                    self._guard(model, *guard, apply)
                except BaseException:
                    self._forget_guard()  # moves left half applied would never be listed again
                    raise
            src = dst
        if src is not state_out:
            state_out.assign(src)
        return state_out
