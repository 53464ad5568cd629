"""Backward-Euler (Baraff-Witkin) mass-spring step: the linear system's pieces (Warp, float64).

One Newton step of backward Euler per substep, linearised at the substep's start
(Baraff & Witkin 1998):

    (M + h Kd + h^2 Kx) dv = h (f(x0, v0) + M g) - h^2 Kx v0,   v1 = v0 + dv,   x1 = x0 + h v1,

with ``Kx = -df/dx`` and ``Kd = -df/dv`` of the springs. Per spring with ``d = x_i - x_j``,
``l = |d|``, ``n = d / l``: ``Kx = ke (n n^T + max(0, 1 - rest / l) (I - n n^T))`` (the transverse
part clamped at 0 for a compressed spring, so the matrix stays positive semi-definite: Choi & Ko
2002) and ``Kd = kd n n^T``, acting on ``p_i - p_j``. Pinned particles (``inv_mass == 0``) keep
``dv = 0``: their rows are the identity and their columns are dropped, so the system is symmetric
positive definite and conjugate gradients apply (:mod:`sim.implicit`).

Every kernel writes a fresh output (``y`` zeroed by the caller before the atomic adds), so the
operator can be replayed on a ``wp.Tape``: the solve's adjoint differentiates
``<lambda, A(x) dv>`` w.r.t. ``x`` and the model's arrays by taping :func:`mass_operator` and
:func:`spring_operator` (implicit differentiation; no CG iteration is ever taped).
"""

import warp as wp

f64 = wp.float64


@wp.kernel
def mass_operator(
    p: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.vec3d),
):
    """``y_i = m_i p_i`` for free particles, ``y_i = p_i`` for pinned ones (identity rows)."""
    i = wp.tid()
    w = inv_mass[i]
    if w == f64(0.0):
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
def spring_operator(
    x: wp.array(dtype=wp.vec3d),
    spring_indices: wp.array(dtype=wp.int32),
    rest_length: wp.array(dtype=wp.float64),
    stiffness: wp.array(dtype=wp.float64),
    damping: wp.array(dtype=wp.float64),
    inv_mass: wp.array(dtype=wp.float64),
    coef_x: wp.float64,
    coef_v: wp.float64,
    p: wp.array(dtype=wp.vec3d),
    y: wp.array(dtype=wp.vec3d),
):
    """Adds ``(coef_x Kx + coef_v Kd) (p_i - p_j)`` of spring ``tid`` to ``y_i`` and subtracts it
    from ``y_j``; pinned particles neither receive nor contribute (their ``p`` counts as 0)."""
    s = wp.tid()
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    n, stretch, ok = spring_frame(x, i, j, rest_length[s])
    if not ok:
        return
    zero = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
    free_i = inv_mass[i] > f64(0.0)
    free_j = inv_mass[j] > f64(0.0)
    pi = zero
    pj = zero
    if free_i:
        pi = p[i]
    if free_j:
        pj = p[j]
    dp = pi - pj
    along = wp.dot(n, dp)
    k = (coef_x * stiffness[s]) * (n * along + stretch * (dp - n * along)) + (coef_v * damping[s] * along) * n
    if free_i:
        wp.atomic_add(y, i, k)
    if free_j:
        wp.atomic_sub(y, j, k)


@wp.kernel
def spring_diagonal(
    x: wp.array(dtype=wp.vec3d),
    spring_indices: wp.array(dtype=wp.int32),
    rest_length: wp.array(dtype=wp.float64),
    stiffness: wp.array(dtype=wp.float64),
    damping: wp.array(dtype=wp.float64),
    inv_mass: wp.array(dtype=wp.float64),
    coef_x: wp.float64,
    coef_v: wp.float64,
    diag: wp.array(dtype=wp.vec3d),
):
    """Adds spring ``tid``'s share of the system's diagonal (per coordinate) to ``diag`` (the
    Jacobi preconditioner; the caller starts it at the masses)."""
    s = wp.tid()
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    n, stretch, ok = spring_frame(x, i, j, rest_length[s])
    if not ok:
        return
    nn = wp.cw_mul(n, n)
    one = wp.vec3d(f64(1.0), f64(1.0), f64(1.0))
    k = (coef_x * stiffness[s]) * (nn + stretch * (one - nn)) + (coef_v * damping[s]) * nn
    if inv_mass[i] > f64(0.0):
        wp.atomic_add(diag, i, k)
    if inv_mass[j] > f64(0.0):
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
    x_out: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3d),
):
    """``v1 = v0 + dv``, ``x1 = x0 + h v1``; pinned particles stay where they are at rest."""
    i = wp.tid()
    if inv_mass[i] == f64(0.0):
        x_out[i] = x[i]
        v_out[i] = wp.vec3d(f64(0.0), f64(0.0), f64(0.0))
        return
    v1 = v[i] + dv[i]
    x_out[i] = x[i] + h * v1
    v_out[i] = v1


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
def cg_step_kernel(
    alpha: wp.float64,
    p: wp.array(dtype=wp.vec3d),
    ap: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
    r: wp.array(dtype=wp.vec3d),
):
    """``x += alpha p``, ``r -= alpha A p`` (in place: CG is never taped)."""
    i = wp.tid()
    x[i] = x[i] + alpha * p[i]
    r[i] = r[i] - alpha * ap[i]


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
