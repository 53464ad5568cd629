"""Backward-Euler (Baraff-Witkin) mass-spring step: the linear system's pieces (Warp, float64).

One Newton step of backward Euler per substep, linearised at the substep's start
(Baraff & Witkin 1998):

    (M + h Kd + h^2 Kx) dv = h (f(x0, v0) + M g) - h^2 Kx v0,   v1 = v0 + dv,   x1 = x0 + h v1,

with ``Kx = -df/dx`` and ``Kd = -df/dv`` of the springs. Per spring with ``d = x_i - x_j``,
``l = |d|``, ``n = d / l``: ``Kx = ke (n n^T + max(0, 1 - rest / l) (I - n n^T))`` (the transverse
part clamped at 0 for a compressed spring, so the matrix stays positive semi-definite: Choi & Ko
2002) and ``Kd = kd n n^T``, acting on ``p_i - p_j``. Pinned particles (``inv_mass == 0``) keep
``dv = 0``: their rows are the identity and their columns are dropped, so the system is symmetric
positive definite and conjugate gradients apply (:mod:`sim.integrators.implicit`).

Every kernel writes a fresh output (``y`` zeroed by the caller before the atomic adds), so the
operator can be replayed on a ``wp.Tape``: the solve's adjoint differentiates
``<lambda, A(x) dv>`` w.r.t. ``x`` and the model's arrays by taping :func:`mass_operator`,
:func:`spring_blocks` and :func:`spring_block_operator` (implicit differentiation; no CG
iteration is ever taped).
"""

import warp as wp

f64 = wp.float64


@wp.kernel
def mass_operator(
    p: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    fixed: wp.array(dtype=wp.int32),
    y: wp.array(dtype=wp.vec3d),
):
    """``y_i = m_i p_i`` for free particles, ``y_i = p_i`` for pinned or ``fixed`` ones (identity
    rows)."""
    i = wp.tid()
    w = inv_mass[i]
    if w == f64(0.0) or fixed[i] != 0:
        y[i] = p[i]
    else:
        y[i] = p[i] / w


@wp.func
def spring_frame(x: wp.array(dtype=wp.vec3d), i: int, j: int, rest: wp.float64):
    """Direction ``n = (x_i - x_j) / l``, the transverse factor ``max(0, 1 - rest / l)`` and
    whether the spring has a direction (``l > 0``) of one spring."""
    d = x[i] - x[j]
    l = wp.length(d)
    if l == f64(0.0):
        return wp.vec3d(f64(0.0), f64(0.0), f64(0.0)), f64(0.0), False
    return d / l, wp.max(f64(1.0) - rest / l, f64(0.0)), True


@wp.kernel
def spring_diagonal(
    spring_indices: wp.array(dtype=wp.int32),
    direction: wp.array(dtype=wp.vec3d),
    along: wp.array(dtype=wp.float64),
    across: wp.array(dtype=wp.float64),
    inv_mass: wp.array(dtype=wp.float64),
    fixed: wp.array(dtype=wp.int32),
    diag: wp.array(dtype=wp.vec3d),
):
    """Adds spring ``tid``'s share of the system's diagonal (per coordinate; its block of
    :func:`spring_blocks`) to ``diag`` (the Jacobi preconditioner; the caller starts it at the
    masses)."""
    s = wp.tid()
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    n = direction[s]
    nn = wp.cw_mul(n, n)
    one = wp.vec3d(f64(1.0), f64(1.0), f64(1.0))
    k = along[s] * nn + across[s] * (one - nn)
    if inv_mass[i] > f64(0.0) and fixed[i] == 0:
        wp.atomic_add(diag, i, k)
    if inv_mass[j] > f64(0.0) and fixed[j] == 0:
        wp.atomic_add(diag, j, k)


@wp.kernel
def implicit_rhs(
    f: wp.array(dtype=wp.vec3d),
    stiff_v0: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    gravity: wp.vec3d,
    h: wp.float64,
    b: wp.array(dtype=wp.vec3d),
):
    """``b_i = h (f_i + m_i g) - (h^2 Kx v0)_i`` for free particles, 0 for pinned ones."""
    i = wp.tid()
    w = inv_mass[i]
    if w == f64(0.0):
        b[i] = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
    else:
        b[i] = h * (f[i] + gravity / w) - stiff_v0[i]


@wp.kernel
def implicit_update(
    x: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    dv: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    h: wp.float64,
    drag: wp.float64,
    x_out: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3d),
):
    """``v1 = (v0 + dv) / (1 + h drag)``, ``x1 = x0 + h v1``; pinned particles stay where
    they are at rest. ``drag``: the linear air drag rate [1/s] (0: none), applied after the
    implicit solve (a splitting: stable at any step, first order like the rest)."""
    i = wp.tid()
    if inv_mass[i] == f64(0.0):
        x_out[i] = x[i]
        v_out[i] = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
        return
    v1 = (v[i] + dv[i]) / (f64(1.0) + h * drag)
    x_out[i] = x[i] + h * v1
    v_out[i] = v1


# ------------------------------------------------------------------ contacts in the solve


@wp.func
def changed(x_pred: wp.vec3d, v_pred: wp.vec3d, x_after: wp.vec3d, v_after: wp.vec3d):
    """Whether the collision stage changed a particle's end position or velocity by more than
    rounding (1e-12 relative): its time-of-impact integration recomputes ``x0 + t v- + (h - t) v+``
    even for a contact without impulse, which differs from the prediction in the last bits."""
    tol = f64(1.0e-12)
    moved = wp.length(x_after - x_pred) > tol * wp.length(x_pred)
    return moved or wp.length(v_after - v_pred) > tol * (wp.length(v_pred) + wp.length(v_after))


@wp.kernel(enable_backward=False)
def collided_particles(
    x_pred: wp.array(dtype=wp.vec3d),
    v_pred: wp.array(dtype=wp.vec3d),
    x_after: wp.array(dtype=wp.vec3d),
    v_after: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    fixed_before: wp.array(dtype=wp.int32),
    excluded: wp.array(dtype=wp.int32),
    fixed: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """``fixed_i = 1`` for the ``fixed_before`` particles and every free particle the collision
    stage moved (:func:`changed`) unless ``excluded_i`` (it touched a rigid body, which must
    feel the reaction: only the collision stage itself moves such a particle); the number of
    particles added goes to ``count[0]`` (a decision: never taped)."""
    i = wp.tid()
    fixed[i] = fixed_before[i]
    if inv_mass[i] == f64(0.0) or fixed_before[i] != 0 or excluded[i] != 0:
        return
    if changed(x_pred[i], v_pred[i], x_after[i], v_after[i]):
        fixed[i] = 1
        wp.atomic_add(count, 0, 1)


@wp.kernel
def constrained_velocity_change(
    x0: wp.array(dtype=wp.vec3d),
    v0: wp.array(dtype=wp.vec3d),
    x_target: wp.array(dtype=wp.vec3d),
    fixed: wp.array(dtype=wp.int32),
    h: wp.float64,
    drag: wp.float64,
    g: wp.array(dtype=wp.vec3d),
):
    """``g_i = (1 + h drag)(x_target_i - x0_i) / h - v0_i`` for ``fixed`` particles (the velocity
    change that ends the substep at ``x_target`` once :func:`implicit_update` has divided the
    velocity by ``1 + h drag``), 0 for the others."""
    i = wp.tid()
    if fixed[i] != 0:
        g[i] = (f64(1.0) + h * drag) * (x_target[i] - x0[i]) / h - v0[i]
    else:
        g[i] = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))


@wp.kernel
def constrained_rhs(
    b: wp.array(dtype=wp.vec3d),
    a_g: wp.array(dtype=wp.vec3d),
    fixed: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.vec3d),
):
    """``out_i = b_i - (A g)_i`` for the unknown particles, 0 for the ``fixed`` ones (whose
    velocity change ``g`` is prescribed)."""
    i = wp.tid()
    if fixed[i] != 0:
        out[i] = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
    else:
        out[i] = b[i] - a_g[i]


@wp.kernel
def sum_kernel(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """``out = a + b`` (a fresh output: taped)."""
    i = wp.tid()
    out[i] = a[i] + b[i]


# ------------------------------------------------------------------ conjugate gradients


@wp.kernel
def dot_kernel(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.dot(a[i], b[i]))


@wp.kernel
def jacobi_kernel(r: wp.array(dtype=wp.vec3d), diag: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    z[i] = wp.cw_div(r[i], diag[i])


@wp.kernel
def spring_blocks(
    x: wp.array(dtype=wp.vec3d),
    spring_indices: wp.array(dtype=wp.int32),
    rest_length: wp.array(dtype=wp.float64),
    stiffness: wp.array(dtype=wp.float64),
    damping: wp.array(dtype=wp.float64),
    coef_x: wp.float64,
    coef_v: wp.float64,
    direction: wp.array(dtype=wp.vec3d),
    along: wp.array(dtype=wp.float64),
    across: wp.array(dtype=wp.float64),
):
    """Each spring's block of ``coef_x Kx + coef_v Kd`` at ``x``: ``along n n^T + across (I - n
    n^T)`` (zero for a spring of zero length). Formed once per solve for CG's products; taped
    (into fresh arrays) where the operator's dependence on ``x`` and the model is differentiated."""
    s = wp.tid()
    n, stretch, ok = spring_frame(x, spring_indices[2 * s], spring_indices[2 * s + 1], rest_length[s])
    direction[s] = n
    if ok:
        along[s] = coef_x * stiffness[s] + coef_v * damping[s]
        across[s] = coef_x * stiffness[s] * stretch
    else:
        along[s] = f64(0.0)
        across[s] = f64(0.0)


@wp.kernel
def spring_block_operator(
    spring_indices: wp.array(dtype=wp.int32),
    direction: wp.array(dtype=wp.vec3d),
    along: wp.array(dtype=wp.float64),
    across: wp.array(dtype=wp.float64),
    inv_mass: wp.array(dtype=wp.float64),
    fixed: wp.array(dtype=wp.int32),
    p: wp.array(dtype=wp.vec3d),
    y: wp.array(dtype=wp.vec3d),
):
    """Adds the blocks' product ``B_s (p_i - p_j)`` of spring ``tid`` (:func:`spring_blocks`) to
    ``y_i`` and subtracts it from ``y_j``; pinned and ``fixed`` particles neither receive nor
    contribute (their ``p`` counts as 0)."""
    s = wp.tid()
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    zero = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
    free_i = inv_mass[i] > f64(0.0) and fixed[i] == 0
    free_j = inv_mass[j] > f64(0.0) and fixed[j] == 0
    pi = zero
    pj = zero
    if free_i:
        pi = p[i]
    if free_j:
        pj = p[j]
    n = direction[s]
    dp = pi - pj
    a = wp.dot(n, dp)
    k = along[s] * a * n + across[s] * (dp - n * a)
    if free_i:
        wp.atomic_add(y, i, k)
    if free_j:
        wp.atomic_sub(y, j, k)


@wp.kernel
def cg_update_kernel(
    alpha: wp.float64,
    p: wp.array(dtype=wp.vec3d),
    ap: wp.array(dtype=wp.vec3d),
    diag: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
    r: wp.array(dtype=wp.vec3d),
    z: wp.array(dtype=wp.vec3d),
    dots: wp.array(dtype=wp.float64),
):
    """One CG update in one pass: ``x += alpha p``, ``r -= alpha A p``, ``z = D^-1 r`` and
    ``dots += (r.r, r.z)`` (the caller zeroes ``dots``; in place: CG is never taped)."""
    i = wp.tid()
    x[i] = x[i] + alpha * p[i]
    ri = r[i] - alpha * ap[i]
    r[i] = ri
    zi = wp.cw_div(ri, diag[i])
    z[i] = zi
    wp.atomic_add(dots, 0, wp.dot(ri, ri))
    wp.atomic_add(dots, 1, wp.dot(ri, zi))


@wp.kernel
def cg_direction_kernel(beta: wp.float64, z: wp.array(dtype=wp.vec3d), p: wp.array(dtype=wp.vec3d)):
    """``p = z + beta p`` (in place)."""
    i = wp.tid()
    p[i] = z[i] + beta * p[i]


@wp.kernel
def add_kernel(a: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """``out += a`` (accumulates an adjoint into an array's gradient)."""
    i = wp.tid()
    out[i] = out[i] + a[i]


@wp.kernel
def negate_kernel(a: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    out[i] = -a[i]


@wp.kernel(enable_backward=False)
def strain_growth(
    x_before: wp.array(dtype=wp.vec3d),
    x_after: wp.array(dtype=wp.vec3d),
    spring_indices: wp.array(dtype=wp.int32),
    rest_length: wp.array(dtype=wp.float64),
    growth: wp.array(dtype=wp.float64),
):
    """``growth[0] = max`` over springs of the increase of the strain ``|x_i - x_j| / rest - 1``
    from ``x_before`` to ``x_after`` (the caller zeroes ``growth``; a decision: never taped)."""
    s = wp.tid()
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    rest = rest_length[s]
    if rest <= f64(0.0):
        return
    change = (wp.length(x_after[i] - x_after[j]) - wp.length(x_before[i] - x_before[j])) / rest
    if change > f64(0.0):
        wp.atomic_max(growth, 0, change)


@wp.kernel
def held_velocity(
    fixed: wp.array(dtype=wp.int32),
    pred_q: wp.array(dtype=wp.vec3d),
    pred_qd: wp.array(dtype=wp.vec3d),
    q: wp.array(dtype=wp.vec3d),
    qd: wp.array(dtype=wp.vec3d),
    trial_qd: wp.array(dtype=wp.vec3d),
    out_qd: wp.array(dtype=wp.vec3d),
):
    """End velocities after a constrained re-solve: a held (``fixed``) particle that the last
    collision stage left as predicted ends with the velocity the trial's collision stage gave it
    (the re-solve moved it along the mean velocity ``(x_target - x0) / h``, which is not its
    velocity after the contact); every other particle keeps ``qd``."""
    i = wp.tid()
    v = qd[i]
    if fixed[i] != 0 and not changed(pred_q[i], pred_qd[i], q[i], qd[i]):
        v = trial_qd[i]
    out_qd[i] = v
