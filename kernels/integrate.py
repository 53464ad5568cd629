"""Time integration and the particle-vs-plane contact (Warp, float64, differentiable).

Every kernel reads the state at the start of a substep and writes *fresh* output arrays (never
the arrays it read), so a ``wp.Tape`` over a rollout can replay the kernels backwards.

* :func:`integrate_particles` — semi-implicit (symplectic) Euler:
  ``v1 = v0 + dt (f inv_mass + g)``, ``x1 = x0 + dt v1``; pinned particles (``inv_mass == 0``)
  keep their position and get zero velocity.
* :func:`integrate_bodies` — rigid bodies. Linear part: the same semi-implicit Euler for the centre
  of mass. Angular part: a kick of the world angular momentum, then a symplectic Lie-group
  splitting of the torque-free rotation (Dullweber, Leimkuhler & McLachlan 1997, "Symplectic
  splitting methods for rigid body molecular dynamics"; Fasso 2003, "Comparison of splitting
  algorithms for the rigid body"). With the principal moments sorted ``I_a <= I_m <= I_c`` (axes
  ``u_a, u_m, u_c`` in the body frame, from ``wp.eig3`` of the body inertia, which need not be
  diagonal: :func:`principal_axes`) the kinetic energy ``T = sum_k L_k^2 / (2 I_k)`` of the
  body-frame momentum is split as ``T = |L|^2 / (2 I_m) + c_c L_c^2 / 2 + c_a L_a^2 / 2`` with
  ``c_k = 1/I_k - 1/I_m`` and ``L_k = u_k . L`` (the intermediate axis' term went into the first
  part, ``c_m = 0``). Every part is exactly integrable: the flow of ``c_k L_k^2 / 2`` for a time
  ``s`` turns the orientation by the angle ``phi = s c_k L_k`` about the body axis ``u_k``
  (``q <- q [u_k, phi]``) and the body-frame momentum the opposite way (``L <- R(u_k, -phi) L``);
  the flow of ``|L|^2 / (2 I_m)`` turns the orientation by ``s |L| / I_m`` about ``L`` itself
  (``L`` stays) and commutes with the other two. One substep ``h`` is the Strang splitting
  ``c (h/2), a (h), c (h/2)`` followed by the ``|L|^2`` rotation for ``h``: second order,
  symplectic, time reversible, with the world angular momentum conserved to rounding (every stage
  is a rotation that leaves ``R L_body`` unchanged) and the energy without drift. It is the DLM
  five-stage splitting ``1 (h/2), 2 (h/2), 3 (h), 2 (h/2), 1 (h/2)`` with the intermediate axis
  absorbed into the exact ``|L|^2`` rotation: one rotation fewer, and exact for symmetric tops
  (``I_a = I_m`` or ``I_m = I_c``: one ``c_k`` is zero) and spheres (both are). The torque is a
  full kick first, ``L = I_w(q0) w0 + h tau`` (world), then the free rotation from ``q0`` with that
  ``L`` for ``h`` — the same kick-then-drift order as the linear semi-implicit Euler; the new
  angular velocity is the one of the new orientation, ``w1 = I_w(q1)^-1 L``. Measured for the free
  box of half extents 0.1 x 0.2 x 0.3 m (density 500, principal moments 1.04, 0.8, 0.4 kg m^2),
  omega0 = (1, 5, 0.1) rad/s, h = 1/480 s: relative energy error bounded by 8e-7 over 50 s without
  drift, world angular momentum to 1.3e-11 (rounding: the stored ``I`` times ``I^-1`` is not
  exactly 1), intermediate-axis flip period within 2e-8 of a scipy reference, second order (the
  previous update, ``w1 = I_w(q1)^-1 L1`` solved by fixed-point iterations, lost 2.5 % of the
  energy in 5 s, 18 % in 50 s, and flipped 9 % early); see ``tests/test_free_rotation.py``.
  Gradients: exact w.r.t. the state; w.r.t. the inertia see :func:`principal_axes_grad`.
* :func:`find_plane_contacts` + :func:`respond_plane_contacts` — particle vs static half-space
  planes with time-of-impact integration ``x(dt) = x0 + t* v- + (dt - t*) v+``,
  ``t* = (offset - n.x0) / (n.v-)`` (design.md "Data flow"): the contact choice is a
  separate non-recorded launch (which plane is hit is piecewise constant), the response is
  differentiable so ``d x(dt) / d v-`` flows through ``t*``.
* :func:`inverse_masses` — particle inverse masses from masses (0 for pinned), taped so that
  ``sim.rollout`` can differentiate w.r.t. the masses.
"""

import warp as wp

from kernels.friction import coulomb_friction
from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE, body_point

f64 = wp.float64


@wp.kernel
def integrate_particles(
    x: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    f: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    gravity: wp.vec3d,
    dt: wp.float64,
    drift: wp.vec3d,
    drag: wp.float64,
    x_out: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3d),
):
    """Semi-implicit Euler for particle ``tid``: ``v1 = v0 + dt (f w + g)``,
    ``x1 = x0 + dt v1 + drift``. ``drift`` is zero, or ``-dt^2 g / 2`` for the exact ballistic
    update: the springs' kick followed by the exact flow of free flight under gravity
    (``x0 + dt (v0 + dt f w) + dt^2 g / 2``; still symplectic, exact for free flight). With a
    linear air ``drag`` rate [1/s], ``v1`` is divided by ``1 + dt drag`` (the drag force
    ``-drag m v1``, implicit: stable at any step)."""
    i = wp.tid()
    w = inv_mass[i]
    if w == f64(0.0):
        x_out[i] = x[i]
        v_out[i] = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
        return
    v1 = (v[i] + (f[i] * w + gravity) * dt) / (f64(1.0) + dt * drag)
    x_out[i] = x[i] + v1 * dt + drift
    v_out[i] = v1


PRINCIPAL_GAP_RTOL = 1.0e-10
"""Relative gap ``|d_i - d_j| / (|d_i| + |d_j|)`` of two principal moments below which the
gradient of :func:`principal_axes` leaves out the turn of their axes within their common plane
(there it has no definite direction: the moments are equal to rounding)."""


DIAGONAL_RTOL = 1.0e-13
"""A body inertia whose off-diagonal entries sum to at most this times its trace counts as
diagonal (mesh axes = principal axes, e.g. an axis-aligned box: off-diagonals ~1e-18 of rounding):
it skips the eigen-decomposition (3/4 of the kernel's cost) at a relative error of the kinetic
energy of the same order."""


@wp.func
def eigen_symmetric(I: wp.mat33d):
    """The forward of :func:`principal_axes` (also recomputed by its adjoint)."""
    off = wp.abs(I[0, 1]) + wp.abs(I[0, 2]) + wp.abs(I[1, 2])
    Q = wp.identity(n=3, dtype=wp.float64)
    d = wp.vec3d(I[0, 0], I[1, 1], I[2, 2])
    if off > f64(DIAGONAL_RTOL) * (wp.abs(I[0, 0]) + wp.abs(I[1, 1]) + wp.abs(I[2, 2])):
        Q, d = wp.eig3(I)
    return Q, d


@wp.func
def principal_axes(I: wp.mat33d):
    """``(Q, d)`` with ``I = Q diag(d) Q^T`` for the symmetric body inertia ``I``: right-handed
    orthonormal principal axes (the columns of ``Q``, body frame) and the principal moments, in no
    particular order (``wp.eig3``, Jacobi: residual ~5e-15 relative in float64; the identity and
    the diagonal for a diagonal ``I``, :data:`DIAGONAL_RTOL`)."""
    Q, d = eigen_symmetric(I)
    return Q, d


@wp.func_grad(principal_axes)
def principal_axes_grad(I: wp.mat33d, adj_Q: wp.mat33d, adj_d: wp.vec3d):
    """Adjoint of :func:`principal_axes` (Giles 2008, "An extended collection of matrix derivative
    results", eigenvalue problem): ``adj_I = Q (diag(adj_d) + F o (Q^T adj_Q)) Q^T``,
    ``F_ij = 1 / (d_j - d_i)``, symmetrised; ``F_ij = 0`` for moments equal to
    :data:`PRINCIPAL_GAP_RTOL` (``wp.eig3``'s own adjoint divides by zero there: a cube's inertia
    gradient was NaN). Only the inertia's gradient goes through here (the state's does not).
    It matches central differences (1e-9) for distinct moments. For equal moments (a cube, a
    symmetric top) the step is still differentiable in the inertia, but a derivative along a
    change that splits the equal moments apart (a cube's ``I_xy``) needs the eigen basis that
    diagonalises the change, not the fixed one: that part of the inertia gradient is not
    recovered (finite, basis dependent). Nothing in the project differentiates w.r.t. the
    inertia (``sim.rollout`` takes states, particle masses and springs)."""
    Q, d = eigen_symmetric(I)
    G = wp.transpose(Q) * adj_Q
    M = wp.mat33d(adj_d[0], f64(0.0), f64(0.0), f64(0.0), adj_d[1], f64(0.0), f64(0.0), f64(0.0), adj_d[2])
    for i in range(3):
        for j in range(3):
            gap = d[j] - d[i]
            if i != j and wp.abs(gap) > f64(PRINCIPAL_GAP_RTOL) * (wp.abs(d[i]) + wp.abs(d[j])):
                M[i, j] = G[i, j] / gap
    A = Q * M * wp.transpose(Q)
    wp.adjoint[I] += f64(0.5) * (A + wp.transpose(A))


@wp.func
def exact_rotation(w: wp.vec3d, s: wp.float64):
    """Unit quaternion of the rotation by the angle ``s |w|`` about ``w`` (``exp(s [w]x)``): the
    one quaternion update of the bodies (free flight, the time-of-impact turns, the push). Smooth
    at ``w = 0`` (a series for angles below 1e-6, truncation ~1e-27), so the tape never
    differentiates ``sqrt(0)``."""
    th2 = s * s * wp.dot(w, w)
    a = f64(0.5) * s * (f64(1.0) - th2 / f64(24.0))  # s sin(th/2) / th
    c = f64(1.0) - th2 / f64(8.0)  # cos(th/2)
    if th2 > f64(1.0e-12):
        th = wp.sqrt(th2)
        a = s * wp.sin(f64(0.5) * th) / th
        c = wp.cos(f64(0.5) * th)
    return wp.quatd(w[0] * a, w[1] * a, w[2] * a, c)


@wp.func
def axis_flow(L: wp.vec3d, u: wp.vec3d, c: wp.float64, s: wp.float64):
    """Exact flow of ``c (u.L)^2 / 2`` for the time ``s`` (``u`` a unit body axis, ``L`` the
    body-frame angular momentum): the orientation turns by ``phi = s c (u.L)`` about ``u`` and
    ``L`` turns back by ``-phi`` (``u.L`` is unchanged). Returns the rotation increment ``dq``:
    the new orientation is ``q dq`` and the new momentum ``rotate_inv(dq, L)``."""
    return wp.quat_from_axis_angle(u, s * c * wp.dot(u, L))  # u is a unit axis: Warp's rotation about it


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
    drift: wp.vec3d,
    body_q_out: wp.array(dtype=wp.transformd),
    body_qd_out: wp.array(dtype=wp.spatial_vectord),
):
    """Rigid body ``tid``; ``body_f`` is the world wrench (torque about the COM, force);
    ``drift`` as in :func:`integrate_particles`.

    A body with ``inv_mass == 0`` keeps its centre of mass (zero linear velocity, no gravity);
    one with zero ``inv_inertia`` keeps its orientation (zero angular velocity). The angular part
    is the kick + splitting of the module docstring.
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
    p1 = p0
    if m_inv > f64(0.0):
        v1 = v0 + (force * m_inv + gravity) * dt
        # drift: zero, or -dt^2 g / 2 for the exact ballistic update (integrate_particles)
        p1 = p0 + v1 * dt + drift

    # angular: kick L = I_w(q0) w0 + dt tau, then the free rotation (c h/2, a h, c h/2, |L|^2 h)
    I_inv_b = inv_inertia[b]
    r1 = r0
    w1 = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
    if wp.ddot(I_inv_b, I_inv_b) > f64(0.0):
        I_b = inertia[b]
        L = wp.quat_rotate(r0, I_b * wp.quat_rotate_inv(r0, w0)) + tau * dt  # world, conserved below
        # principal axes (columns of Q, body frame) and moments, sorted: a smallest, c largest,
        # m the intermediate one (ties give distinct indices: all equal -> a 0, m 1, c 2)
        Q, d = principal_axes(I_b)
        ia = int(0)
        if d[1] < d[ia]:
            ia = 1
        if d[2] < d[ia]:
            ia = 2
        ic = int(2)
        if d[1] > d[ic]:
            ic = 1
        if d[0] > d[ic]:
            ic = 0
        im = 3 - ia - ic
        Qt = wp.transpose(Q)
        u_a = Qt[ia]
        u_c = Qt[ic]
        inv_m = f64(1.0) / d[im]
        c_a = f64(1.0) / d[ia] - inv_m
        c_c = f64(1.0) / d[ic] - inv_m
        half = f64(0.5) * dt

        Lb = wp.quat_rotate_inv(r0, L)
        dq1 = axis_flow(Lb, u_c, c_c, half)
        Lb1 = wp.quat_rotate_inv(dq1, Lb)
        dq2 = axis_flow(Lb1, u_a, c_a, dt)
        Lb2 = wp.quat_rotate_inv(dq2, Lb1)
        dq3 = axis_flow(Lb2, u_c, c_c, half)
        Lb3 = wp.quat_rotate_inv(dq3, Lb2)
        dq4 = exact_rotation(Lb3, dt * inv_m)  # the flow of |L|^2 / 2 in the body frame
        r1 = wp.normalize(r0 * dq1 * dq2 * dq3 * dq4)
        w1 = wp.quat_rotate(r1, I_inv_b * wp.quat_rotate_inv(r1, L))

    body_q_out[b] = wp.transformd(p1, r1)
    body_qd_out[b] = wp.spatial_vectord(w1[0], w1[1], w1[2], v1[0], v1[1], v1[2])


@wp.func
def time_of_impact_position(x0: wp.vec3d, v_minus: wp.vec3d, v_plus: wp.vec3d, ts: wp.float64, h: wp.float64):
    """``x0 + t* v- + (h - t*) v+``: the end of a substep ``h`` [s] whose velocity switches from
    ``v-`` to ``v+`` at the time of impact ``ts`` [s] (the one time-of-impact integration: the
    particles' plane contacts here, and the collision response's particles and bodies,
    :mod:`kernels.pose`)."""
    return x0 + ts * v_minus + (h - ts) * v_plus


@wp.func
def earliest_plane(x0: wp.vec3d, v: wp.vec3d, planes: wp.array(dtype=wp.vec4d), plane_count: int,
                   separation: wp.float64, dt: wp.float64) -> int:
    """The first plane that a point moving from ``x0`` [m] at ``v`` [m/s] for ``dt`` [s] comes
    within ``separation`` [m] of (or -1): it moves inwards (``n.v < 0``) and ends inside
    (``n.(x0 + dt v) < offset + separation``); a point that starts inside gets ``t* = 0``. The
    one plane test of particles (:func:`find_plane_contacts`) and sphere bodies (whose
    ``separation`` adds the radius, :mod:`kernels.spheres`)."""
    best = int(-1)
    best_t = dt
    x1 = x0 + v * dt
    for k in range(plane_count):
        p = planes[k]
        n = wp.vec3d(p[0], p[1], p[2])
        off = p[3] + separation
        vn = wp.dot(n, v)
        if vn < f64(0.0) and wp.dot(n, x1) - off < f64(0.0):
            t = wp.max(f64(0.0), (off - wp.dot(n, x0)) / vn)
            if best < 0 or t < best_t:
                best = k
                best_t = t
    return best


@wp.kernel(enable_backward=False)
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
    if inv_mass[i] > f64(0.0):
        best = earliest_plane(x0[i], v[i], planes, plane_count, thickness, dt)
    plane_index[i] = wp.int32(best)


@wp.func
def rebound_normal_velocity(vn_at: f64, after: f64, half_gravity: f64, restitution: f64) -> f64:
    """The plane-contact law's normal velocity [m/s] after an impact (derived in
    :func:`respond_plane_contacts`), never into the surface: ``vn_at`` (at ``t*``, with gravity's
    ``half_gravity``) reflected by ``restitution``, plus the forces' inward change ``after``
    ``t*``, less ``half_gravity``. :func:`plane_rebound` and the mesh contacts share it."""
    vn_plus = wp.max(after, f64(0.0))
    if restitution > f64(0.0):
        vn_plus = wp.max(-restitution * wp.min(vn_at, f64(0.0)) + after - half_gravity, f64(0.0))
    return vn_plus


@wp.func
def plane_rebound(n: wp.vec3d, v_start: wp.vec3d, v: wp.vec3d, toi: wp.float64, dt: wp.float64, gravity: wp.vec3d,
                  drift: wp.vec3d, restitution: wp.float64) -> wp.float64:
    """The normal velocity [m/s] after a plane impact at ``toi`` [s] within a substep ``dt`` [s]
    whose velocity goes from ``v_start`` (its start) to ``v`` (predicted, after the forces): the
    one plane-contact law of particles (:func:`respond_plane_contacts`) and sphere bodies
    (:mod:`kernels.spheres`); the derivation is in :func:`respond_plane_contacts`."""
    # the forces' normal velocity change over the substep, where it points into the plane
    # (gravity on a floor); an outward one (springs lifting a resting cloth) is left out of the
    # reflection: adding it after the impact let a resting, inelastic cloth hop on the ground
    change_n = wp.min(wp.dot(n, v - v_start), f64(0.0))
    half_gravity = f64(0.5) * wp.min(wp.dot(n, gravity) * dt, f64(0.0))
    if wp.length_sq(drift) > f64(0.0):
        # the exact ballistic update stores the velocity at the substep's end, not its middle:
        # no half substep of gravity, and the path's drift on top of the straight-line positions
        half_gravity = f64(0.0)
    after = change_n * (f64(1.0) - toi / dt)
    vn_at = wp.dot(n, v_start) + change_n * (toi / dt) + half_gravity
    return rebound_normal_velocity(vn_at, after, half_gravity, restitution)


@wp.kernel
def respond_plane_contacts(
    x0: wp.array(dtype=wp.vec3d),
    v_start: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    planes: wp.array(dtype=wp.vec4d),
    plane_index: wp.array(dtype=wp.int32),
    restitution: wp.float64,
    friction: wp.float64,
    thickness: wp.float64,
    gravity: wp.vec3d,
    dt: wp.float64,
    drift: wp.vec3d,
    x_out: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3d),
):
    """Time-of-impact integration of particle ``tid`` against ``planes[plane_index[tid]]``.

    Without contact: ``x1 = x0 + dt v + drift`` (``drift`` as in :func:`integrate_particles`).
    With the exact ballistic update (``drift`` not zero) the stored velocity is the one at the
    substep's end: the half substep of gravity below is left out and ``drift`` is added to the
    time-of-impact position (under constant gravity that is the exact parabola through the
    impact at ``t*``). With contact: ``t* = clamp((off - n.x0) / n.v, 0, dt)``
    on the straight path of the predicted velocity ``v``; the normal velocity is reflected as it
    is *at* ``t*`` and the forces' change after ``t*`` is added afterwards (the result not let
    point into the plane), for the part of the change that points into the plane,
    ``c = min(n.(v - v_start), 0)``. Semi-implicit Euler's stored velocity is the one of the
    middle of the substep before: under a constant force its positions lie on the exact path
    whose velocity at ``t`` is the stored one at ``t + dt/2``. So gravity's inward part
    ``g_n = min(n.g dt, 0)`` (the constant force; springs are left as they are) enters the
    velocity at ``t*`` over half a substep more, ``v_n(t*) = n.v_start + c t*/dt + g_n / 2``,
    and a bouncing particle (``e > 0``) stores the velocity after the impact less that half
    substep of gravity, ``v+_n = max(-e min(v_n(t*), 0) + c (1 - t*/dt) - g_n / 2, 0)``: with
    ``x1 = x0 + t* v + (dt - t*) v+`` the bounce of a free particle under gravity is exact (an
    apex ratio of ``e^2`` to 1e-5 at 8 substeps of 1/60 s; without the half substep it was
    ``g dt (1 + e) / (e v)`` low, 1.4 %). An inelastic impact (``e = 0``) leaves the particle
    resting on the plane, ``v+_n = max(c (1 - t*/dt), 0) = 0``. Reflecting all of ``v`` instead
    made the bounce depend on whether it falls at the end of one substep or the start of the
    next. The tangential part ``v_t`` loses at most ``mu`` times the normal velocity change
    (Coulomb, clamped at sticking). One impact per substep (the earliest plane).
    """
    i = wp.tid()
    xi = x0[i]
    vi = v[i]
    k = plane_index[i]
    if k < 0:
        if inv_mass[i] > f64(0.0):
            x_out[i] = xi + vi * dt + drift
        else:  # pinned: never moved by the drift
            x_out[i] = xi + vi * dt
        v_out[i] = vi
        return
    p = planes[k]
    n = wp.vec3d(p[0], p[1], p[2])
    off = p[3] + thickness
    vn = wp.dot(n, vi)
    toi = wp.clamp((off - wp.dot(n, xi)) / vn, f64(0.0), dt)

    vn_plus = plane_rebound(n, v_start[i], vi, toi, dt, gravity, drift, restitution)
    vt = vi - n * vn
    jn = vn_plus - vn  # normal velocity change, >= 0
    vt_plus = vt + coulomb_friction(-vt, vt, friction * jn)  # velocity changes of a unit mass
    v_plus = vt_plus + n * vn_plus

    x_out[i] = time_of_impact_position(xi, vi, v_plus, toi, dt) + drift
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


@wp.kernel(enable_backward=False)
def outside_bounds_kernel(
    particle_q: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.transformd),
    body_qd: wp.array(dtype=wp.spatial_vectord),
    particle_count: int,
    center: wp.vec3d,
    radius: wp.float64,
    flag: wp.array(dtype=wp.int32),
):
    """Divergence check (a decision, off the tape): sets ``flag[0] = 1`` when a particle's or a
    body's position or velocity is not finite, or its position lies farther than ``radius`` [m]
    from ``center`` [m]. Thread ``tid`` checks particle ``tid`` (``tid < particle_count``), else
    body ``tid - particle_count``."""
    tid = wp.tid()
    if tid < particle_count:
        x = particle_q[tid]
        v = particle_qd[tid]
        ok = wp.isfinite(x) and wp.isfinite(v)
    else:
        b = tid - particle_count
        x = wp.transform_get_translation(body_q[b])
        ok = wp.isfinite(x) and wp.isfinite(wp.transform_get_rotation(body_q[b])) and wp.isfinite(body_qd[b])
    if not ok:
        flag[0] = 1
    elif wp.length(x - center) > radius:
        flag[0] = 1


@wp.func
def quat_turn(q: wp.quatd, omega: wp.vec3d, duration: wp.float64) -> wp.quatd:
    """``q`` turned by the world angular velocity ``omega`` [rad/s] for ``duration`` [s]: the
    exact rotation (:func:`exact_rotation`), renormalised."""
    return wp.normalize(exact_rotation(omega, duration) * q)


@wp.func
def time_of_impact_pose(X: wp.transformd, v_minus: wp.spatial_vectord, v_plus: wp.spatial_vectord, ts: wp.float64,
                        h: wp.float64):
    """The same for a body pose: the centre of mass as a particle, the orientation turned by
    ``w-`` for ``t*`` and by ``w+`` for ``h - t*`` (twists angular, linear)."""
    p = time_of_impact_position(wp.transform_get_translation(X), wp.spatial_bottom(v_minus), wp.spatial_bottom(v_plus),
                                ts, h)
    r = quat_turn(quat_turn(wp.transform_get_rotation(X), wp.spatial_top(v_minus), ts), wp.spatial_top(v_plus), h - ts)
    return wp.transformd(p, r)


@wp.kernel
def time_of_impact_kernel(
    particle_count: int,
    x0: wp.array(dtype=wp.vec3d),
    x_pred: wp.array(dtype=wp.vec3d),
    particle_v_minus: wp.array(dtype=wp.vec3d),
    particle_v_plus: wp.array(dtype=wp.vec3d),
    particle_v_moving: wp.array(dtype=wp.vec3d),
    particle_contact: wp.array(dtype=wp.int32),
    q0: wp.array(dtype=wp.transformd),
    q_pred: wp.array(dtype=wp.transformd),
    body_v_minus: wp.array(dtype=wp.spatial_vectord),
    body_v_plus: wp.array(dtype=wp.spatial_vectord),
    body_v_moving: wp.array(dtype=wp.spatial_vectord),
    body_contact: wp.array(dtype=wp.int32),
    toi: wp.array(dtype=wp.float64),
    h: wp.float64,
    x1: wp.array(dtype=wp.vec3d),
    q1: wp.array(dtype=wp.transformd),
):
    """Time-of-impact integration of particle ``tid`` (first ``particle_count`` threads;
    :func:`time_of_impact_position`) and of body ``tid - particle_count``
    (:func:`time_of_impact_pose`) with the ``t*`` of its earliest contact row (-1: no contact,
    the prediction stays; -2: impact zone, its rigid motion from ``t* = 0``), plus the push:
    the moving velocities' excess over ``v+`` (``v_moving - v+``, the separation restored at
    the position level) as a displacement over the whole substep ``h``, whatever ``t*`` is (a
    contact found at the end of the substep still ends separated: ending it touching would
    leave the next substep no side to push it to)."""
    i = wp.tid()
    if i < particle_count:
        k = particle_contact[i]
        if k == -1:
            x1[i] = x_pred[i]
        elif k == -2:
            x1[i] = x0[i] + h * particle_v_moving[i]
        else:
            x1[i] = time_of_impact_position(x0[i], particle_v_minus[i], particle_v_plus[i], toi[k], h) + h * (
                particle_v_moving[i] - particle_v_plus[i])
        return
    b = i - particle_count
    kb = body_contact[b]
    if kb == -1:
        q1[b] = q_pred[b]
        return
    ts = wp.float64(0.0)
    if kb >= 0:
        ts = toi[kb]
    pose = time_of_impact_pose(q0[b], body_v_minus[b], body_v_plus[b], ts, h)
    push = body_v_moving[b] - body_v_plus[b]
    q1[b] = wp.transformd(wp.transform_get_translation(pose) + h * wp.spatial_bottom(push),
                          quat_turn(wp.transform_get_rotation(pose), wp.spatial_top(push), h))


@wp.func
def planned_position(x0: wp.vec3d, x_pred: wp.vec3d, v_minus: wp.vec3d, v_plus: wp.vec3d, ts: wp.float64,
                     h: wp.float64) -> wp.vec3d:
    """The Gauss-Seidel response's plan (not taped) of one particle: :func:`time_of_impact_position`
    at its earliest contact time ``ts`` [s] (inf: none, the prediction ``x_pred`` stays; 0 for
    an impact zone's)."""
    if wp.isinf(ts):
        return x_pred
    return time_of_impact_position(x0, v_minus, v_plus, ts, h)


@wp.func
def planned_pose(q0: wp.transformd, q_pred: wp.transformd, v_minus: wp.spatial_vectord, v_plus: wp.spatial_vectord,
                 ts: wp.float64, h: wp.float64) -> wp.transformd:
    """The same for a body's pose (:func:`time_of_impact_pose`)."""
    if wp.isinf(ts):
        return q_pred
    return time_of_impact_pose(q0, v_minus, v_plus, ts, h)


@wp.kernel
def planned_substep_kernel(
    particle_q0: wp.array(dtype=wp.vec3d),
    particle_q_pred: wp.array(dtype=wp.vec3d),
    particle_v_minus: wp.array(dtype=wp.vec3d),
    particle_v_plus: wp.array(dtype=wp.vec3d),
    particle_time: wp.array(dtype=wp.float64),
    body_q0: wp.array(dtype=wp.transformd),
    body_q_pred: wp.array(dtype=wp.transformd),
    body_v_minus: wp.array(dtype=wp.spatial_vectord),
    body_v_plus: wp.array(dtype=wp.spatial_vectord),
    body_time: wp.array(dtype=wp.float64),
    h: wp.float64,
    vertex_type: wp.array(dtype=wp.int32),
    vertex_owner: wp.array(dtype=wp.int32),
    local: wp.array(dtype=wp.vec3d),
    particle_count: int,
    body_count: int,
    particle_q1: wp.array(dtype=wp.vec3d),
    body_q1: wp.array(dtype=wp.transformd),
    x1: wp.array(dtype=wp.vec3d),
):
    """The Gauss-Seidel response's plan in one launch: the particles' ends
    (:func:`planned_position`) in the first ``P`` threads, the bodies' (:func:`planned_pose`)
    in the next ``B``, then the vertices posed at those ends (:func:`pose_vertices_kernel`), each
    vertex thread working out its owner's end itself (no thread waits for another's).
    Launched over ``P + B + vertices`` threads (``P``, ``B``: ``particle_count``,
    ``body_count``), or over ``P + B`` for the ends alone (the caller then poses the vertices
    from them, :func:`pose_vertices_kernel`: bodies with many vertices would otherwise
    integrate their pose once per vertex)."""
    i = wp.tid()
    P = particle_count
    B = body_count
    if i < P:
        particle_q1[i] = planned_position(particle_q0[i], particle_q_pred[i], particle_v_minus[i], particle_v_plus[i],
                                          particle_time[i], h)
        return
    if i < P + B:
        b = i - P
        body_q1[b] = planned_pose(body_q0[b], body_q_pred[b], body_v_minus[b], body_v_plus[b], body_time[b], h)
        return
    v = i - P - B
    kind = vertex_type[v]
    o = vertex_owner[v]
    if kind == VERTEX_PARTICLE:
        x1[v] = planned_position(particle_q0[o], particle_q_pred[o], particle_v_minus[o], particle_v_plus[o],
                                 particle_time[o], h)
    elif kind == VERTEX_BODY:
        x1[v] = body_point(planned_pose(body_q0[o], body_q_pred[o], body_v_minus[o], body_v_plus[o], body_time[o], h),
                           local[v])
    else:
        x1[v] = local[v]
