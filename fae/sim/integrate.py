"""One substep of every particle in one pass: anchor, muscles, integration, layer order, contact.

The springs' forces come in `particle_f` (fae.sim.springs); each
particle then adds its muscle influences (its rows of the model's per-particle arrays) and
takes a symplectic Euler step in which its velocity drag c and its anchor (a zero-length
spring of stiffness k_a to its hold: its rest place carried by the skull, the jaw, or a
blend of both, `particle_jaw`) are implicit:

    v' = (v + h/m (f + k_a (hold - x)) + h c_a u) / (1 + h c + h^2 k_a / m),   x' = x + h v'.

The bones move over a step from the Control's poses at its start to those at its end: the
hold moves with them, substep by substep, at velocity u, and the particle's carried drag
c_a (`particle_carried_drag`, a share of c: fae.sim.build.carried_share) resists motion
relative to it, the rest of c absolute motion. Tissue is carried by the bone beneath it:
the whole drag against the jaw's carry left the chin 110 ms behind the mandible, and a lip
whose FAP takes back part of that carry through its muscles first moved the wrong way;
the lips carried as much as the chin ran past their place as the jaw opened, the muscles'
take-back still lagging.

The drag and the anchor are per particle (diagonal), so implicit costs nothing more than
explicit, and they widen the stable substep (see fae.sim.solver): the anchors are the
stiffest part of the skin, and the drag also damps the springs' fastest modes. The
stiffness of contracted muscles (fae.sim.muscles) joins k_a in the denominator: a
linearized implicit step for them, which changes no equilibrium (at rest v' = v = 0 and
f = 0 whatever the denominator). Only the springs are explicit.

Then the layer order: an epidermis particle is kept at least `particle_height` above the
previous position of its own vertex in the middle layer, along its rest normal carried by
its hold (a position projection; the inward normal velocity is removed). Without it an
epidermis pushed through the middle layer is a stable state of the springs: the skin of
the eyelids and brows stayed sunk 3 mm after 10,000 random frames. Last, a collider
particle that entered the skull or the mandible is projected out (fae.sim.collision), the
skull first.

Particles with zero inverse mass sit on their hold. On the CPU each thread steps `chunk`
consecutive particles (the kernel's many arguments are copied once per thread: 1.0 ms per
pass one per thread, 0.58 ms in chunks of 64 on the shipped head).
"""

from __future__ import annotations

import warp as wp

from fae.sim.collision import skull_then_jaw_contact, sphere_contact
from fae.sim.muscles import muscle_direction

# fast math: about 1.5x faster kernels on the CPU; the numpy reference still agrees to 1e-5.
# No adjoint code: nothing is differentiated (kernels compile in 0.6x the time).
wp.set_module_options({"fast_math": True, "enable_backward": False})


@wp.struct
class ParticleStatic:
    """A particle's constants in one record (made by fae.sim.solver from the model's arrays:
    one array read per particle instead of eleven, each of which a Warp kernel also tests
    for a negative index; the pass is 18 % faster on the CPU). Fields as the SkinModel's
    particle_q (rest), particle_jaw, particle_inv_mass, particle_anchor_stiffness,
    row_influence_start[i] and [i + 1], particle_below, particle_normal, particle_height,
    particle_collider, particle_clearance, particle_sphere, particle_sphere_max, particle_drag,
    particle_carried_drag."""

    rest: wp.vec3
    jaw: float
    inv_mass: float
    anchor_stiffness: float
    influence_first: int
    influence_end: int
    below: int
    normal: wp.vec3
    height: float
    collider: int
    clearance: wp.vec2
    sphere: wp.vec4
    sphere_max: float
    drag: float
    carried_drag: float


@wp.kernel
def step_particles(particle_q: wp.array(dtype=wp.vec3), particle_qd: wp.array(dtype=wp.vec3),
                   particle_f: wp.array(dtype=wp.vec3), particle_static: wp.array(dtype=ParticleStatic),
                   influence_muscle: wp.array(dtype=int), influence_weight: wp.array(dtype=float),
                   muscle_kind: wp.array(dtype=int), muscle_point_now: wp.array(dtype=wp.vec3),
                   muscle_axis_u_now: wp.array(dtype=wp.vec3), muscle_axis_v_now: wp.array(dtype=wp.vec3),
                   muscle_scale: wp.array(dtype=float),
                   muscle_activation: wp.array(dtype=float), bone_rotation: wp.array(dtype=wp.mat33),
                   bone_translation: wp.array(dtype=wp.vec3),
                   head_sdf: wp.array3d(dtype=float), head_sdf_origin: wp.vec3, head_sdf_spacing: float,
                   jaw_sdf: wp.array3d(dtype=float), jaw_sdf_origin: wp.vec3, jaw_sdf_spacing: float,
                   contact_depth: float, dt: float, step_phase: wp.array(dtype=float), particle_count: int,
                   chunk: int, particle_q_out: wp.array(dtype=wp.vec3), particle_qd_out: wp.array(dtype=wp.vec3)):
    start = wp.tid() * chunk
    R0 = bone_rotation[0]
    R1 = bone_rotation[1]
    t0 = bone_translation[0]
    t1 = bone_translation[1]
    # the bones at the step's start (fae.sim.model.POSE_COUNT); the holds move from there
    R2 = bone_rotation[2]
    R3 = bone_rotation[3]
    t2 = bone_translation[2]
    t3 = bone_translation[3]
    reached = step_phase[0]  # the share of the step done at this substep's end
    substep_share = step_phase[1]  # h / the step's length: 1 / substeps
    for tid in range(start, wp.min(start + chunk, particle_count)):
        ps = particle_static[tid]
        rest = ps.rest
        jaw = ps.jaw
        end = (R0 * rest + t0) * (1.0 - jaw) + (R1 * rest + t1) * jaw
        begin = (R2 * rest + t2) * (1.0 - jaw) + (R3 * rest + t3) * jaw
        target = begin + (end - begin) * reached
        # h u, the hold's move in this substep (u itself would need 1 / dt, which overflows
        # float32 for a frame shorter than 3e-39 s)
        carried = (end - begin) * substep_share
        w = ps.inv_mass
        if w == 0.0:
            particle_q_out[tid] = target
            particle_qd_out[tid] = wp.vec3(0.0, 0.0, 0.0)
            continue
        x0 = particle_q[tid]
        x = x0
        v = particle_qd[tid]
        f = particle_f[tid]
        ka = ps.anchor_stiffness
        for r in range(ps.influence_first, ps.influence_end):
            m = influence_muscle[r]
            act = muscle_activation[m]
            if act != 0.0:
                dirm, km = muscle_direction(x, muscle_kind[m], muscle_point_now[m], muscle_axis_u_now[m],
                                            muscle_axis_v_now[m], muscle_scale[m])
                f = f + dirm * (act * influence_weight[r])
                ka = ka + km * wp.abs(act) * influence_weight[r]
        f = f + (target - x) * ps.anchor_stiffness
        # the drag resists motion relative to the hold: skin carried by a moving bone
        # is not held back (tissue moves with the bone beneath it)
        v = (v + f * (w * dt) + carried * ps.carried_drag) / (1.0 + dt * ps.drag + dt * dt * w * ka)
        x = x + v * dt
        k = ps.below
        if k >= 0:
            # layer order: no closer to the layer below than a fraction of the rest height,
            # along the rest normal carried by the hold
            n0 = ps.normal
            n = wp.normalize(R0 * n0 * (1.0 - jaw) + R1 * n0 * jaw)
            gap = ps.height - wp.dot(x - particle_q[k], n)
            if gap > 0.0:
                x = x + n * gap
                vn = wp.dot(v, n)
                if vn < 0.0:
                    v = v - n * vn
        if ps.collider != 0:
            # the bones are where the step ends, and so is the hold that tells their sides
            x, v = skull_then_jaw_contact(x0, x, v, rest, end, ps.clearance, head_sdf, head_sdf_origin,
                                          head_sdf_spacing, R0, t0, jaw_sdf, jaw_sdf_origin, jaw_sdf_spacing, R1, t1,
                                          contact_depth)
        if ps.sphere[3] > 0.0 or ps.sphere_max > 0.0:
            x, v = sphere_contact(x, v, ps.sphere, ps.sphere_max, R0, t0)
        particle_qd_out[tid] = v
        particle_q_out[tid] = x
