"""Time integration and the particle-vs-plane contact (Warp, float64, differentiable).

Every kernel reads the state at the start of a substep and writes *fresh* output arrays (never
the arrays it read), so a ``wp.Tape`` over a rollout can replay the kernels backwards.

* :func:`integrate_particles` — semi-implicit (symplectic) Euler:
  ``v1 = v0 + dt (f inv_mass + g)``, ``x1 = x0 + dt v1``; pinned particles (``inv_mass == 0``)
  keep their position and get zero velocity.
* :func:`integrate_bodies` — rigid bodies. Linear part: the same semi-implicit Euler for the centre
  of mass. Angular part: momentum form of semi-implicit Euler. The world angular momentum is
  updated explicitly, ``L1 = I_w(q0) w0 + dt tau`` with ``I_w(q) = R I R^T``, and the new angular
  velocity is the one consistent with the *new* orientation, ``w1 = I_w(q1)^-1 L1``, where
  ``q1 = normalize(q0 + dt/2 [w1, 0] q0)``. The gyroscopic term is not dropped: to first order
  ``I_w(q1)^-1 I_w(q0) w0 = w0 - dt I_w^-1 (w0 x I_w w0)``, which is the explicit predictor the
  fixed-point iteration starts from. Torque-free bodies keep ``L`` to the fixed-point residual
  ``~(dt |w|)^(k+1)`` per step instead of the explicit gyroscopic update's O(dt^2) per step.
  Measured for a symmetric top (I = diag(1, 1, 2), body w = (0.3, 0, 2) rad/s, 1000 steps):
  relative drift of L about 2e-4 with the explicit update at dt = 1e-3, 3e-13 with this one at
  dt = 1e-3 and 1.4e-8 at dt = 1/60; see ``tests/test_integrator.py``.
* :func:`find_plane_contacts` + :func:`respond_plane_contacts` — particle vs static half-space
  planes with time-of-impact integration ``x(dt) = x0 + t* v- + (dt - t*) v+``,
  ``t* = (offset - n.x0) / (n.v-)`` (design.md "Data flow"): the contact choice is a
  separate non-recorded launch (which plane is hit is piecewise constant), the response is
  differentiable so ``d x(dt) / d v-`` flows through ``t*``.
* :func:`inverse_masses` — particle inverse masses from masses (0 for pinned), taped so that
  ``sim.rollout`` can differentiate w.r.t. the masses.
"""

import warp as wp

f64 = wp.float64

GYROSCOPIC_ITERATIONS = wp.constant(4)
"""Fixed-point iterations for ``w1 = I_w(q1(w1))^-1 L1``. The map contracts by about ``dt |w|``
per iteration; from the explicit gyroscopic predictor (error O((dt|w|)^2)) four iterations leave a
residual ~(dt|w|)^6, e.g. 1e-18 at dt |w| = 1e-3 and 1e-8 at dt |w| = 0.05. A constant count keeps
the loop unrolled, hence differentiable by the tape."""


@wp.kernel
def integrate_particles(
    x: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    f: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    gravity: wp.vec3d,
    dt: wp.float64,
    x_out: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3d),
):
    """Semi-implicit Euler for particle ``tid``: ``v1 = v0 + dt (f w + g)``, ``x1 = x0 + dt v1``."""
    i = wp.tid()
    w = inv_mass[i]
    if w == f64(0.0):
        x_out[i] = x[i]
        v_out[i] = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
        return
    v1 = v[i] + (f[i] * w + gravity) * dt
    x_out[i] = x[i] + v1 * dt
    v_out[i] = v1


@wp.func
def quat_step(q0: wp.quatd, w: wp.vec3d, dt: wp.float64):
    """``normalize(q0 + dt/2 [w, 0] q0)`` (world-frame angular velocity, xyzw quaternion)."""
    dq = wp.quatd(w[0], w[1], w[2], f64(0.0)) * q0
    return wp.normalize(q0 + dq * (f64(0.5) * dt))


@wp.kernel
def integrate_bodies(
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    body_f: wp.array(dtype=wp.spatial_vectord),
    inv_mass: wp.array(dtype=wp.float64),
    inertia: wp.array(dtype=wp.mat33d),
    inv_inertia: wp.array(dtype=wp.mat33d),
    gravity: wp.vec3d,
    dt: wp.float64,
    body_q_out: wp.array(dtype=wp.transformd),
    body_qd_out: wp.array(dtype=wp.spatial_vectord),
):
    """Rigid body ``tid``; ``body_f`` is the world wrench (torque about the COM, force).

    A body with ``inv_mass == 0`` keeps its centre of mass (zero linear velocity, no gravity);
    one with zero ``inv_inertia`` keeps its orientation.
    """
    b = wp.tid()
    X = body_q[b]
    p0 = wp.transform_get_translation(X)
    r0 = wp.transform_get_rotation(X)
    twist = body_qd[b]
    w0 = wp.spatial_top(twist)
    v0 = wp.spatial_bottom(twist)
    wrench = body_f[b]
    tau = wp.spatial_top(wrench)
    force = wp.spatial_bottom(wrench)

    # linear: semi-implicit Euler of the centre of mass
    m_inv = inv_mass[b]
    v1 = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
    if m_inv > f64(0.0):
        v1 = v0 + (force * m_inv + gravity) * dt
    p1 = p0 + v1 * dt

    # angular: L1 = I_w(q0) w0 + dt tau, w1 = I_w(q1)^-1 L1 with q1 = quat_step(q0, w1)
    I_b = inertia[b]
    I_inv_b = inv_inertia[b]
    R0 = wp.quat_to_matrix(r0)
    Iw0 = R0 * I_b * wp.transpose(R0)
    Iw0_inv = R0 * I_inv_b * wp.transpose(R0)
    Iw0_w0 = Iw0 * w0
    L1 = Iw0_w0 + tau * dt
    # explicit gyroscopic predictor
    w1 = w0 + Iw0_inv * (tau - wp.cross(w0, Iw0_w0)) * dt
    for _k in range(GYROSCOPIC_ITERATIONS):
        r1 = quat_step(r0, w1, dt)
        w1 = wp.quat_rotate(r1, I_inv_b * wp.quat_rotate_inv(r1, L1))
    r1 = quat_step(r0, w1, dt)

    body_q_out[b] = wp.transformd(p1, r1)
    body_qd_out[b] = wp.spatial_vectord(w1[0], w1[1], w1[2], v1[0], v1[1], v1[2])


@wp.func
def time_of_impact_position(x0: wp.vec3d, v_minus: wp.vec3d, v_plus: wp.vec3d, ts: wp.float64, h: wp.float64):
    """``x0 + t* v- + (h - t*) v+``: the end of a substep ``h`` [s] whose velocity switches from
    ``v-`` to ``v+`` at the time of impact ``ts`` [s] (the one time-of-impact integration: the
    particles' plane contacts here, and the collision response's particles and bodies,
    :mod:`kernels.contact`)."""
    return x0 + ts * v_minus + (h - ts) * v_plus


@wp.kernel
def find_plane_contacts(
    x0: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    planes: wp.array(dtype=wp.vec4d),
    plane_count: int,
    thickness: wp.float64,
    dt: wp.float64,
    plane_index: wp.array(dtype=wp.int32),
):
    """Earliest plane crossed by ``x0 -> x0 + dt v`` (or -1). Not differentiated (launch it with
    ``record_tape=False``): the dynamic loop and the argmin are piecewise constant.

    A plane counts when the particle moves inwards (``n.v < 0``) and ends inside
    (``n.(x0 + dt v) < offset + thickness``); a particle that already starts inside gets
    ``t* = 0``. Pinned particles never collide.
    """
    i = wp.tid()
    best = int(-1)
    best_t = dt
    if inv_mass[i] > f64(0.0):
        xi = x0[i]
        vi = v[i]
        x1 = xi + vi * dt
        for k in range(plane_count):
            p = planes[k]
            n = wp.vec3d(p[0], p[1], p[2])
            off = p[3] + thickness
            vn = wp.dot(n, vi)
            if vn < f64(0.0) and wp.dot(n, x1) - off < f64(0.0):
                t = wp.max(f64(0.0), (off - wp.dot(n, xi)) / vn)
                if best < 0 or t < best_t:
                    best = k
                    best_t = t
    plane_index[i] = wp.int32(best)


@wp.kernel
def respond_plane_contacts(
    x0: wp.array(dtype=wp.vec3d),
    v_start: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    planes: wp.array(dtype=wp.vec4d),
    plane_index: wp.array(dtype=wp.int32),
    restitution: wp.float64,
    friction: wp.float64,
    thickness: wp.float64,
    dt: wp.float64,
    x_out: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3d),
):
    """Time-of-impact integration of particle ``tid`` against ``planes[plane_index[tid]]``.

    Without contact: ``x1 = x0 + dt v``. With contact: ``t* = clamp((off - n.x0) / n.v, 0, dt)``
    on the straight path of the predicted velocity ``v``; the normal velocity is reflected as it
    is *at* ``t*`` (the forces' change ``v - v_start`` of the substep split at ``t*``: the part
    before the impact is reflected, the part after it is added afterwards, and the result is
    not let point into the plane), for the part of the change that points into the plane,
    ``c = min(n.(v - v_start), 0)``: ``v+_n = max(-e min(n.v_start + c t*/dt, 0) + c (1 - t*/dt), 0)``. Reflecting all of ``v``
    instead made the bounce depend on whether it falls at the end of one substep or the start of
    the next (gravity's ``g dt`` reflected or not: a jump of ``2 g dt`` in the velocity, 1.6 cm
    in a bank shot's end point). The tangential part ``v_t`` loses at most ``mu`` times the
    normal velocity change (Coulomb, clamped at sticking); ``x1 = x0 + t* v + (dt - t*) v+``.
    One impact per substep (the earliest plane).
    """
    i = wp.tid()
    xi = x0[i]
    vi = v[i]
    k = plane_index[i]
    if k < 0:
        x_out[i] = xi + vi * dt
        v_out[i] = vi
        return
    p = planes[k]
    n = wp.vec3d(p[0], p[1], p[2])
    off = p[3] + thickness
    vn = wp.dot(n, vi)
    toi = wp.clamp((off - wp.dot(n, xi)) / vn, f64(0.0), dt)

    # the forces' normal velocity change over the substep, where it points into the plane
    # (gravity on a floor); an outward one (springs lifting a resting cloth) is left out of the
    # reflection: adding it after the impact let a resting, inelastic cloth hop on the ground
    change_n = wp.min(wp.dot(n, vi - v_start[i]), f64(0.0))
    vn_at = wp.dot(n, v_start[i]) + change_n * (toi / dt)
    vn_plus = wp.max(-restitution * wp.min(vn_at, f64(0.0)) + change_n * (f64(1.0) - toi / dt), f64(0.0))
    vt = vi - n * vn
    jn = vn_plus - vn  # normal velocity change, >= 0
    vt_len = wp.length(vt)
    vt_plus = vt
    if vt_len > f64(0.0):
        vt_plus = vt * wp.max(f64(0.0), f64(1.0) - friction * jn / vt_len)
    v_plus = vt_plus + n * vn_plus

    x_out[i] = time_of_impact_position(xi, vi, v_plus, toi, dt)
    v_out[i] = v_plus


@wp.kernel
def inverse_masses(mass: wp.array(dtype=wp.float64), inv_mass: wp.array(dtype=wp.float64)):
    """``inv_mass = 1 / mass`` for ``mass > 0`` and 0 for pinned particles (``mass == 0``), into
    a fresh array; taped, so gradients w.r.t. the inverse masses reach the masses
    (``d inv / d m = -1 / m^2``; none for pinned particles)."""
    i = wp.tid()
    m = mass[i]
    if m > f64(0.0):
        inv_mass[i] = f64(1.0) / m
    else:
        inv_mass[i] = f64(0.0)
