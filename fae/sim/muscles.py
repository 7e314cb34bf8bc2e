"""Muscle forces: Waters linear muscles, elliptic sphincters and directional pull fields.

Each muscle acts on the particles listed in the model's influence arrays with a weight
precomputed at build time (Waters' angular and radial fall-off inside the zone of
influence, the sphincter's elliptic fall-off, or a pull field's radial fall-off, all
masked by skin regions), so a step only multiplies activation x weight x direction:

- linear:    towards the attachment's current position (it moves with its bone);
- sphincter: towards the centre, within the sphincter's plane, proportional to the
             offset from the centre divided by the larger semi-axis;
- field:     along a fixed direction of the bone's frame.

Once per step `pose_muscles` carries every muscle's point and axes by its bone; the
solver's particle pass (fae.sim.integrate) then gathers each particle's influences and
calls `muscle_direction`. A contracted sphincter or linear muscle is also a stiffness (its force
turns with the particle: activation x weight / semi-axis, or / distance to the
attachment); the pass treats it implicitly like the anchors, so that a strong contraction
cannot make the explicit substep unstable (the orbicularis oris at its limit is stiffer than
all the springs).
"""

from __future__ import annotations

import warp as wp

# fast math: about 1.5x faster kernels on the CPU; the numpy reference still agrees to 1e-5.
# No adjoint code: nothing is differentiated (kernels compile in 0.6x the time).
wp.set_module_options({"fast_math": True, "enable_backward": False})


@wp.kernel
def pose_muscles(muscle_bone: wp.array(dtype=int), muscle_point: wp.array(dtype=wp.vec3),
                 muscle_axis_u: wp.array(dtype=wp.vec3), muscle_axis_v: wp.array(dtype=wp.vec3),
                 bone_rotation: wp.array(dtype=wp.mat33), bone_translation: wp.array(dtype=wp.vec3),
                 point_now: wp.array(dtype=wp.vec3), axis_u_now: wp.array(dtype=wp.vec3),
                 axis_v_now: wp.array(dtype=wp.vec3)):
    """Each muscle's attachment or centre and axes carried by its bone, once per step (the
    particle pass would otherwise transform them once per influence)."""
    m = wp.tid()
    b = muscle_bone[m]
    R = bone_rotation[b]
    point_now[m] = R * muscle_point[m] + bone_translation[b]
    axis_u_now[m] = R * muscle_axis_u[m]
    axis_v_now[m] = R * muscle_axis_v[m]


@wp.func
def muscle_direction(x: wp.vec3, kind: int, point: wp.vec3, axis_u: wp.vec3, axis_v: wp.vec3, scale: float):
    """(force, stiffness) per unit activation and weight on a particle at x, given the muscle's
    posed point and axes (`pose_muscles`): the force (see the module docstring) and the
    largest eigenvalue of minus its Jacobian in x (1/m), which the particle pass makes
    implicit."""
    f = wp.vec3(0.0, 0.0, 0.0)
    k = float(0.0)
    if kind == 0:
        d = point - x
        length = wp.length(d)
        if length > 1.0e-9:
            f = d / length
            k = 1.0 / wp.max(length, 1.0e-3)
    elif kind == 1:
        d = x - point
        f = -(axis_u * wp.dot(d, axis_u) + axis_v * wp.dot(d, axis_v)) / scale
        k = 1.0 / scale
    else:
        f = axis_u
    return f, k
