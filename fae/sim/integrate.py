"""One substep of every particle in one pass: anchor, muscles, integration, layer order, contact.

The springs' forces come in `particle_f` (a scatter over springs, fae.sim.springs); each
particle then adds its muscle influences (its rows of the model's per-particle arrays) and
takes a symplectic Euler step in which its velocity drag c and its anchor (a zero-length
spring of stiffness k_a to its hold: its rest place carried by the skull, the jaw, or a
blend of both, `particle_jaw`) are implicit:

    v' = (v + h/m (f + k_a (hold - x))) / (1 + h c + h^2 k_a / m),   x' = x + h v'.

Both are per particle (diagonal), so implicit costs nothing more than explicit, and they
widen the stable substep (see fae.sim.solver): the anchors are the stiffest part of the
skin, and the drag also damps the springs' fastest modes. The stiffness of contracted muscles (fae.sim.muscles) joins k_a in the denominator:
a linearized implicit step for them, which changes no equilibrium (at rest v' = v = 0 and
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

from fae.sim.collision import bone_contact
from fae.sim.muscles import muscle_direction

# fast math: about 1.5x faster kernels on the CPU; the numpy reference still agrees to 1e-5.
# No adjoint code: nothing is differentiated (kernels compile in 0.6x the time).
wp.set_module_options({"fast_math": True, "enable_backward": False})


@wp.kernel
def step_particles(particle_q: wp.array(dtype=wp.vec3), particle_qd: wp.array(dtype=wp.vec3),
                   particle_f: wp.array(dtype=wp.vec3), particle_inv_mass: wp.array(dtype=float),
                   particle_rest: wp.array(dtype=wp.vec3), particle_jaw: wp.array(dtype=float),
                   particle_anchor_stiffness: wp.array(dtype=float),
                   row_influence_start: wp.array(dtype=int), influence_muscle: wp.array(dtype=int),
                   influence_weight: wp.array(dtype=float),
                   muscle_kind: wp.array(dtype=int), muscle_point_now: wp.array(dtype=wp.vec3),
                   muscle_axis_u_now: wp.array(dtype=wp.vec3), muscle_axis_v_now: wp.array(dtype=wp.vec3),
                   muscle_scale: wp.array(dtype=float),
                   muscle_activation: wp.array(dtype=float), bone_rotation: wp.array(dtype=wp.mat33),
                   bone_translation: wp.array(dtype=wp.vec3), particle_below: wp.array(dtype=int),
                   particle_normal: wp.array(dtype=wp.vec3), particle_height: wp.array(dtype=float),
                   particle_collider: wp.array(dtype=int), particle_clearance: wp.array(dtype=wp.vec2),
                   head_sdf: wp.array3d(dtype=float), head_sdf_origin: wp.vec3, head_sdf_spacing: float,
                   jaw_sdf: wp.array3d(dtype=float), jaw_sdf_origin: wp.vec3, jaw_sdf_spacing: float,
                   contact_depth: float, damping: float, dt: float, particle_count: int, chunk: int,
                   particle_q_out: wp.array(dtype=wp.vec3), particle_qd_out: wp.array(dtype=wp.vec3)):
    start = wp.tid() * chunk
    for tid in range(start, wp.min(start + chunk, particle_count)):
        rest = particle_rest[tid]
        jaw = particle_jaw[tid]
        target = (bone_rotation[0] * rest + bone_translation[0]) * (1.0 - jaw) \
            + (bone_rotation[1] * rest + bone_translation[1]) * jaw
        w = particle_inv_mass[tid]
        if w == 0.0:
            particle_q_out[tid] = target
            particle_qd_out[tid] = wp.vec3(0.0, 0.0, 0.0)
            continue
        x = particle_q[tid]
        v = particle_qd[tid]
        f = particle_f[tid]
        ka = particle_anchor_stiffness[tid]
        for r in range(row_influence_start[tid], row_influence_start[tid + 1]):
            m = influence_muscle[r]
            act = muscle_activation[m]
            if act != 0.0:
                dirm, km = muscle_direction(x, muscle_kind[m], muscle_point_now[m], muscle_axis_u_now[m],
                                            muscle_axis_v_now[m], muscle_scale[m])
                f = f + dirm * (act * influence_weight[r])
                ka = ka + km * wp.abs(act) * influence_weight[r]
        f = f + (target - x) * particle_anchor_stiffness[tid]
        v = (v + f * (w * dt)) / (1.0 + dt * damping + dt * dt * w * ka)
        x = x + v * dt
        k = particle_below[tid]
        if k >= 0:
            # layer order: no closer to the layer below than a fraction of the rest height,
            # along the rest normal carried by the hold
            n0 = particle_normal[tid]
            n = wp.normalize(bone_rotation[0] * n0 * (1.0 - jaw) + bone_rotation[1] * n0 * jaw)
            gap = particle_height[tid] - wp.dot(x - particle_q[k], n)
            if gap > 0.0:
                x = x + n * gap
                vn = wp.dot(v, n)
                if vn < 0.0:
                    v = v - n * vn
        if particle_collider[tid] != 0:
            x0 = particle_q[tid]
            clear = particle_clearance[tid]
            x, v = bone_contact(x0, x, v, rest, target, clear[0], head_sdf, head_sdf_origin, head_sdf_spacing, bone_rotation[0],
                                bone_translation[0], contact_depth)
            x, v = bone_contact(x0, x, v, rest, target, clear[1], jaw_sdf, jaw_sdf_origin, jaw_sdf_spacing, bone_rotation[1],
                                bone_translation[1], contact_depth)
        particle_qd_out[tid] = v
        particle_q_out[tid] = x
