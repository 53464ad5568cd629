"""Batched numpy and torch access to the robust root solver of :mod:`kernels.roots`.

Every function accepts coefficients with any number of leading batch dimensions and returns
arrays with the same leading shape. There is one implementation of the solver (Warp, float64);
these functions only validate input, launch its kernels and reshape the output.

The numpy functions take ``precision="float32"`` (the same solver generated in float32 by
:mod:`kernels.variants`: coefficients rounded to float32, computed in float32, results returned
as float64 / complex128 for comparison) and the knobs ``max_iterations`` / ``tolerance`` of its
Newton-bisection (``None``: the kernels' 256 and 2 ulp). The defaults run the original kernels.

Example:
    >>> import numpy as np
    >>> from collision.roots import solve_cubic
    >>> solve_cubic(np.array([1.0, -6.0, 11.0, -6.0]))      # (t-1)(t-2)(t-3)
    array([1.+0.j, 2.+0.j, 3.+0.j])
"""

from __future__ import annotations

import numpy as np
import warp as wp

from core.device import init_warp
from kernels import roots as _k
from kernels import variants as _variants

DEFAULT_T_MAX = _k.DEFAULT_T_MAX
DEFAULT_MAX_DERIVATIVE = _k.DEFAULT_MAX_DERIVATIVE
PRECISIONS = _variants.PRECISIONS
"""Precisions of the numpy API: ``"float64"`` (default) and ``"float32"``."""
FLOAT32_T_MAX = _variants.T_MAX["float32"]
"""In float32 ``t_max`` is capped at this (float32(1e18) = 9.999999843067494e17: ``t_max^2`` must
stay a finite float32); a t_max below it is rounded to float32."""

__all__ = [
    "DEFAULT_MAX_DERIVATIVE",
    "DEFAULT_T_MAX",
    "DERIVATIVES",
    "FLOAT32_T_MAX",
    "PRECISIONS",
    "cubic_root_jacobian",
    "cubic_roots",
    "orthogonal_clamped_jacobian",
    "quadratic_root_jacobian",
    "quadratic_roots",
    "solve_cubic",
    "solve_quadratic",
]

DERIVATIVES = ("mollified", "orthogonal")
"""Root derivatives on offer: ``mollified`` (the kernels' robust division, bounded by ``M``
everywhere) and ``orthogonal`` (eq. ``orthogonal_clamping_real_side``: a real root's exact
implicit derivative with only its component along the merging direction clamped to ``M``; complex
and escaping roots keep the mollified one). See :func:`orthogonal_clamped_jacobian`."""

ORTHOGONAL_ROOT_LIMIT = 1.0e3
"""Real roots beyond this magnitude (of the polynomial scaled to a largest coefficient of 1) keep
the mollified row under ``derivative="orthogonal"``: a nearly escaping root (``q`` small, ``t``
near ``-a/q``) has an exact derivative growing like ``|t|^3 / |p'(t)|`` (1e16 at ``q = 1e-8``)
that has nothing to do with a merging pair, and the robust division bounds it."""

_DEVICE = "cpu"


def _check_coefficients(p, n: int, name: str = "p") -> np.ndarray:
    """Validated float64 copy of ``p`` with last dimension ``n``."""
    arr = np.asarray(p)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{name}: expected a numeric array of coefficients, got dtype {arr.dtype}")
    if np.iscomplexobj(arr):
        raise ValueError(f"{name}: coefficients must be real, got complex dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != n:
        raise ValueError(f"{name}: expected shape (..., {n}), got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        idx = np.argwhere(bad)
        shown = ", ".join(f"{name}[{', '.join(map(str, i))}]={arr[tuple(i)]!r}" for i in idx[:5])
        more = f" (and {len(idx) - 5} more)" if len(idx) > 5 else ""
        raise ValueError(f"{name}: coefficients must be finite; non-finite entries: {shown}{more}")
    return arr


def _check_positive(value: float, name: str) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def launch_root_kernel(kernel, coefficients: np.ndarray, coef_type, scalars: list, outputs: list, scalar=wp.float64):
    """Launch ``kernel`` over the rows of ``coefficients``; outputs come back as numpy arrays.

    On the CPU the numpy buffers are shared with Warp (no copies in or out). ``scalar`` is the
    kernels' float type (``wp.float32`` for a float32 variant: ``coefficients`` must then be
    float32 and the outputs are float32).
    """
    init_warp()
    flat = np.ascontiguousarray(coefficients.reshape(-1, coefficients.shape[-1]))
    count = flat.shape[0]
    np_dtype = np.float64 if scalar is wp.float64 else np.float32
    results = [np.empty((count,) + tuple(dtype._shape_), dtype=np_dtype) for dtype in outputs]
    if count == 0:
        return results
    coef = wp.array(flat, dtype=coef_type, device=_DEVICE, copy=False)
    outs = [wp.array(r, dtype=dtype, device=_DEVICE, copy=False) for r, dtype in zip(results, outputs)]
    wp.launch(kernel, dim=count, inputs=[coef, *[scalar(s) for s in scalars]], outputs=outs, device=_DEVICE)
    wp.synchronize_device(_DEVICE)
    return results


_VARIANTS: dict = {}


def root_kernels(precision, max_iterations, tolerance):
    """The roots kernel module for the settings: :mod:`kernels.roots` itself for the defaults,
    else the generated variant (:func:`kernels.variants.kernel_variant`, cached here)."""
    if precision == "float64" and max_iterations is None and tolerance is None:
        return _k
    key = (precision, max_iterations, tolerance, type(max_iterations), type(tolerance))  # True != 1 here
    mod = _VARIANTS.get(key)
    if mod is None:
        init_warp()
        mod = _variants.kernel_variant(precision, max_iterations=max_iterations, tolerance=tolerance).roots
        _VARIANTS[key] = mod
    return mod


def _variant_inputs(k, arr: np.ndarray, t_max: float, name: str = "p"):
    """(coefficients, t_max, vec3 type, vec4 type, float type) for launching the kernels of
    module ``k``: for a float32 variant the coefficients are rounded to float32 (non-finite after
    rounding is a ValueError naming the entries) and ``t_max`` is capped at :data:`FLOAT32_T_MAX`."""
    if k.f64 is wp.float64:
        return arr, t_max, wp.vec3d, wp.vec4d, wp.float64
    with np.errstate(over="ignore"):
        arr32 = arr.astype(np.float32)
    bad = ~np.isfinite(arr32)
    if bad.any():
        idx = np.argwhere(bad)
        shown = ", ".join(f"{name}[{', '.join(map(str, i))}]={arr[tuple(i)]!r}" for i in idx[:5])
        raise ValueError(f"{name}: coefficients overflow float32 (precision='float32'): {shown}")
    return arr32, min(t_max, FLOAT32_T_MAX), wp.vec3f, wp.vec4f, wp.float32


def _to_complex(flat_roots: np.ndarray, lead_shape: tuple, slots: int) -> np.ndarray:
    # (re, im) pairs are laid out like complex128: a view, not a copy
    return flat_roots.reshape(-1, 2 * slots).view(np.complex128).reshape(lead_shape + (slots,))


def solve_quadratic(p, t_max: float = DEFAULT_T_MAX, *, precision: str = "float64", max_iterations=None,
                    tolerance=None) -> np.ndarray:
    """All roots of ``a t^2 + b t + c``.

    Args:
        p: coefficients ``[a, b, c]``, shape (..., 3), finite.
        t_max: magnitude at which escaping roots are clamped (the paper's 1e150; capped at
            :data:`FLOAT32_T_MAX` in float32).
        precision: ``"float64"`` or ``"float32"`` (coefficients rounded to float32 and solved in
            float32 arithmetic by the generated variant of the same kernels; results converted
            to complex128).
        max_iterations: Newton-bisection iteration cap (positive int; None: 256). The quadratic
            is closed form, so it has no effect here; accepted for symmetry with :func:`solve_cubic`.
        tolerance: Newton relative step tolerance (positive; None: 2 ulp of the precision); no
            effect on the quadratic either.

    Returns:
        complex128 array (..., 2): slots ``(t-, t+)`` with ``t+ = (-b + sqrt(b^2 - 4ac)) / 2a``;
        for a complex pair ``t+`` carries ``+sqrt(4ac - b^2) / 2a``. ``a = 0`` uses the paper's
        pseudo-sign of ``a``; ``a = b = c = 0`` gives a double root at 0.

    Raises:
        ValueError: wrong shape or non-finite coefficients (the message names the entries;
            float32: also coefficients that overflow float32), or a bad ``precision`` /
            ``max_iterations`` / ``tolerance`` (named).
    """
    k = root_kernels(precision, max_iterations, tolerance)
    arr = _check_coefficients(p, 3)
    t_max = _check_positive(t_max, "t_max")
    if k is _k:
        (roots,) = launch_root_kernel(_k.solve_quadratic_kernel, arr, wp.vec3d, [t_max], [wp.vec4d])
        return _to_complex(roots, arr.shape[:-1], 2)
    arr_k, t_max, v3, v4, scalar = _variant_inputs(k, arr, t_max)
    (roots,) = launch_root_kernel(k.solve_quadratic_kernel, arr_k, v3, [t_max], [v4], scalar)
    return _to_complex(roots.astype(np.float64), arr.shape[:-1], 2)


def solve_cubic(p, t_max: float = DEFAULT_T_MAX, *, precision: str = "float64", max_iterations=None,
                tolerance=None) -> np.ndarray:
    """All roots of ``q t^3 + a t^2 + b t + c``.

    Args:
        p: coefficients ``[q, a, b, c]``, shape (..., 4), finite.
        t_max: magnitude at which escaping roots are clamped (capped at :data:`FLOAT32_T_MAX` in
            float32).
        precision: ``"float64"`` or ``"float32"`` (see :func:`solve_quadratic`).
        max_iterations: Newton-bisection iteration cap per real root (positive int; None: 256).
        tolerance: relative Newton step below which a root is accepted (positive; None: 2 ulp of
            the precision, 2^-51 / 2^-22).

    Returns:
        complex128 array (..., 3): slots ``(t-, tM, t+)``. Three real roots ascend; a single real
        root is ``t+`` when it lies right of the complex pair's real part (reduced ``c^ <= 0``),
        else ``t-``, and the larger-labelled slot of the pair holds ``+Im``. ``q = 0``: the
        escaping root is ``-sign(a) t_max``; all zero: triple root 0.

    Raises:
        ValueError: wrong shape or non-finite coefficients, or a bad knob (named).
    """
    k = root_kernels(precision, max_iterations, tolerance)
    arr = _check_coefficients(p, 4)
    t_max = _check_positive(t_max, "t_max")
    if k is _k:
        (roots,) = launch_root_kernel(_k.solve_cubic_kernel, arr, wp.vec4d, [t_max], [_k.vec6d])
        return _to_complex(roots, arr.shape[:-1], 3)
    arr_k, t_max, _, v4, scalar = _variant_inputs(k, arr, t_max)
    (roots,) = launch_root_kernel(k.solve_cubic_kernel, arr_k, v4, [t_max], [k.vec6d], scalar)
    return _to_complex(roots.astype(np.float64), arr.shape[:-1], 3)


def _quadratic_jacobian_raw(arr: np.ndarray, t_max: float, max_derivative: float, k=_k):
    if k is not _k:
        arr_k, t_max, v3, v4, scalar = _variant_inputs(k, arr, t_max)
        roots, jac = launch_root_kernel(k.quadratic_jacobian_kernel, arr_k, v3, [t_max, max_derivative], [v4, k.mat43d], scalar)
        roots, jac = roots.astype(np.float64), jac.astype(np.float64)
    else:
        roots, jac = launch_root_kernel(
            _k.quadratic_jacobian_kernel, arr, wp.vec3d, [t_max, max_derivative], [wp.vec4d, _k.mat43d]
        )
    lead = arr.shape[:-1]
    return roots.reshape(lead + (2, 2)), jac.reshape(lead + (2, 2, 3))


def _cubic_jacobian_raw(arr: np.ndarray, t_max: float, max_derivative: float, k=_k):
    if k is not _k:
        arr_k, t_max, _, v4, scalar = _variant_inputs(k, arr, t_max)
        roots, jac = launch_root_kernel(k.cubic_jacobian_kernel, arr_k, v4, [t_max, max_derivative], [k.vec6d, k.mat64d], scalar)
        roots, jac = roots.astype(np.float64), jac.astype(np.float64)
    else:
        roots, jac = launch_root_kernel(_k.cubic_jacobian_kernel, arr, wp.vec4d, [t_max, max_derivative], [_k.vec6d, _k.mat64d])
    lead = arr.shape[:-1]
    return roots.reshape(lead + (3, 2)), jac.reshape(lead + (3, 2, 4))


def _check_derivative(derivative: str) -> str:
    if derivative not in DERIVATIVES:
        raise ValueError(f"derivative must be one of {DERIVATIVES}, got {derivative!r}")
    return derivative


def orthogonal_clamped_jacobian(p, roots, jacobian, max_derivative: float = DEFAULT_MAX_DERIVATIVE,
                                t_max: float = DEFAULT_T_MAX) -> np.ndarray:
    """Eq. ``orthogonal_clamping_real_side``, generalised from the paper's monic quadratic.

    A real root's exact implicit derivative ``g = -v(t) / p'(t)``, ``v(t) = [t^(n-1), ..., t, 1]``,
    blows up where two real roots merge (``p'(t) -> 0``). The paper splits it into a part along
    ``dc~/dp^`` (the direction that moves the parabola ``c~ = 0``, i.e. that separates or merges
    the pair) and the rest, and clamps only the first. For any polynomial that direction is
    ``n = v(t_c)``, the gradient of ``p(t_c)`` at the critical point ``p'(t_c) = 0`` between the
    pair (for the monic quadratic ``p(t_c) = c~`` and ``v(t_c) = [-b^/2, 1] = dc~/dp^``):
    ``g = alpha n + g_perp`` with ``alpha`` clamped to ``|alpha| <= M``. ``g_perp`` stays bounded
    as the roots merge (it tends to ``-(dv/dt(t_c))_perp / p''(t_c)``); it is evaluated from
    divided differences, without the cancellation of ``g - alpha n``. The clamp is taken on the
    polynomial scaled to a largest coefficient of 1 (``M`` unit-free, as for the mollified
    derivative). Complex roots, roots beyond :data:`ORTHOGONAL_ROOT_LIMIT`, and imaginary parts
    keep the rows of ``jacobian``. The split is taken in the space of *all* the coefficients
    (``n = [t_c^2, t_c, 1]`` for a quadratic); the paper projects on ``(b^, c^)`` only, with the
    leading one fixed at 1, so a loss that holds the leading coefficient fixed sees an extra,
    bounded part along ``[t_c, 1]`` compared with the paper's equation.

    Args:
        p: coefficients (..., n), highest degree first, n = 3 (quadratic) or 4 (cubic).
        roots: (..., n-1, 2) their roots (Re, Im) from the solver.
        jacobian: (..., n-1, 2, n) the solver's mollified Jacobian (the rows kept as they are).
        max_derivative: the clamp ``M`` (> 0) of the parallel part.
        t_max: the solver's root clamp (roots at it are the escaping ones).

    Returns:
        float64 (..., n-1, 2, n): ``jacobian`` with the real roots' real-part rows replaced.
    """
    arr = np.asarray(p, dtype=np.float64)
    n = arr.shape[-1]
    if n not in (3, 4):
        raise ValueError(f"p must hold 3 or 4 coefficients, got {n}")
    max_derivative = _check_positive(max_derivative, "max_derivative")
    roots = np.asarray(roots, dtype=np.float64)
    out = np.array(jacobian, dtype=np.float64, copy=True)
    scale = np.abs(arr).max(axis=-1, keepdims=True)
    scale = np.where(scale > 0.0, scale, 1.0)
    pc = arr / scale  # unit-scaled coefficients
    if n == 3:
        pc = np.concatenate([np.zeros_like(pc[..., :1]), pc], axis=-1)  # as a cubic with q = 0
    q, a, b = pc[..., 0:1], pc[..., 1:2], pc[..., 2:3]  # (..., 1): broadcast over the root slots
    t = roots[..., 0]
    real = (roots[..., 1] == 0.0) & (np.abs(t) <= min(ORTHOGONAL_ROOT_LIMIT, t_max)) & np.isfinite(t)
    t = np.where(real, t, 0.0)
    # critical points: roots of p'(t) = 3q t^2 + 2a t + b; the one nearest t (their common real
    # part when they are complex: the root is then isolated and the split still well defined)
    disc = a * a - 3.0 * q * b
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        # the two roots of 3q t^2 + 2a t + b without cancellation (q may be 0: then the linear one)
        lead = -(a + np.copysign(sq, a))
        c1 = np.where(lead != 0.0, b / lead, np.nan)
        c2 = np.where(q != 0.0, lead / (3.0 * q), np.nan)
        c_inflect = np.where(q != 0.0, -a / (3.0 * q), np.where(a != 0.0, -b / (2.0 * a), 0.0))
    has_real = (disc >= 0.0) & ((q != 0.0) | (a != 0.0))
    c1 = np.where(np.isfinite(c1), c1, np.inf)
    c2 = np.where(np.isfinite(c2), c2, np.inf)
    nearer = np.where(np.abs(t - c1) <= np.abs(t - c2), c1, c2)
    tc = np.where(has_real, nearer, c_inflect)
    tc = np.where(np.isfinite(tc), tc, 0.0)
    powers = np.arange(3, -1, -1)
    v_c = tc[..., None] ** powers  # n = v(t_c), (..., slots, 4)
    # divided differences w = (v(t) - v(t_c)) / (t - t_c) and p'(t) / (t - t_c) (exact when
    # p'(t_c) = 0): g_perp = -(w - proj_n w) / d
    w = np.stack([t * t + t * tc + tc * tc, t + tc, np.ones_like(t), np.zeros_like(t)], axis=-1)
    d = 3.0 * q * (t + tc) + 2.0 * a
    dp = 3.0 * q * t * t + 2.0 * a * t + b
    if n == 3:
        v_c, w = v_c[..., 1:], w[..., 1:]
    nn = (v_c * v_c).sum(-1)
    v_t = t[..., None] ** powers[4 - n:]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        alpha = -(v_t * v_c).sum(-1) / nn / dp
        perp_exact = -(w - ((w * v_c).sum(-1) / nn)[..., None] * v_c) / d[..., None]
        g = -v_t / dp[..., None]
        perp_direct = g - (alpha[..., None] * v_c)
    perp = np.where((has_real & (d != 0.0))[..., None], perp_exact, perp_direct)
    # a double root (p'(t) = 0) or a non-finite split: the sign of the mollified row's parallel part
    moll = np.take(out, 0, axis=-2) * scale[..., None, :]  # d Re / d(unit-scaled p)
    sign_moll = np.sign((moll * v_c).sum(-1))
    with np.errstate(invalid="ignore", over="ignore"):
        # a zero sign (no mollified direction) gives a NaN row here: the mollified row is kept
        alpha = np.where(np.isfinite(alpha), alpha, sign_moll * np.inf)
        alpha = np.clip(alpha, -max_derivative, max_derivative)
        row = (alpha[..., None] * v_c + perp) / scale[..., None, :]
    ok = real & np.isfinite(row).all(-1)
    out[..., 0, :] = np.where(ok[..., None], row, out[..., 0, :])
    return out


def quadratic_root_jacobian(
    p, t_max: float = DEFAULT_T_MAX, max_derivative: float = DEFAULT_MAX_DERIVATIVE, *, precision: str = "float64",
    max_iterations=None, tolerance=None,
) -> np.ndarray:
    """Mollified Jacobian of both quadratic roots (eq. ``ourapproachderivctilde``).

    Args:
        p: ``[a, b, c]``, shape (..., 3).
        t_max: root clamp.
        max_derivative: ``M`` of the robust division.
        precision: as for :func:`solve_quadratic` (float32: computed in float32, returned as
            float64).
        max_iterations: as for :func:`solve_quadratic`.
        tolerance: as for :func:`solve_quadratic`.

    Returns:
        float64 (..., 2, 2, 3): ``[slot (t-, t+), part (Re, Im), coefficient (a, b, c)]``.
    """
    k = root_kernels(precision, max_iterations, tolerance)
    arr = _check_coefficients(p, 3)
    _, jac = _quadratic_jacobian_raw(
        arr, _check_positive(t_max, "t_max"), _check_positive(max_derivative, "max_derivative"), k
    )
    return jac


def cubic_root_jacobian(p, t_max: float = DEFAULT_T_MAX, max_derivative: float = DEFAULT_MAX_DERIVATIVE, *,
                        precision: str = "float64", max_iterations=None, tolerance=None) -> np.ndarray:
    """Mollified Jacobian of the three cubic roots w.r.t. the caller's coefficients.

    Args:
        p: ``[q, a, b, c]``, shape (..., 4).
        t_max: root clamp.
        max_derivative: ``M`` of the robust division.
        precision: as for :func:`solve_cubic`.
        max_iterations: as for :func:`solve_cubic`.
        tolerance: as for :func:`solve_cubic`.

    Returns:
        float64 (..., 3, 2, 4): ``[slot (t-, tM, t+), part (Re, Im), coefficient (q, a, b, c)]``.
    """
    k = root_kernels(precision, max_iterations, tolerance)
    arr = _check_coefficients(p, 4)
    _, jac = _cubic_jacobian_raw(arr, _check_positive(t_max, "t_max"), _check_positive(max_derivative, "max_derivative"), k)
    return jac


# ---------------------------------------------------------------------------------------------
# torch autograd functions
# ---------------------------------------------------------------------------------------------


def _torch_roots(p, n: int, jac_fn, t_max: float, max_derivative: float, derivative: str = "mollified"):
    import torch

    if _check_derivative(derivative) == "orthogonal":
        mollified = jac_fn

        def jac_fn(arr, t_max, max_derivative):
            roots, jac = mollified(arr, t_max, max_derivative)
            return roots, orthogonal_clamped_jacobian(arr, roots, jac, max_derivative, t_max)

    class _Roots(torch.autograd.Function):
        @staticmethod
        def forward(ctx, coefficients):
            arr = _check_coefficients(coefficients.detach().cpu().numpy(), n, name="p")
            roots, jac = jac_fn(arr, t_max, max_derivative)
            ctx.save_for_backward(torch.from_numpy(jac).to(coefficients.device))
            return torch.from_numpy(roots).to(device=coefficients.device, dtype=coefficients.dtype)

        @staticmethod
        def backward(ctx, grad_roots):
            (jac,) = ctx.saved_tensors
            # grad_p[..., k] = sum_{slot, part} grad[..., slot, part] * J[..., slot, part, k]
            return torch.einsum("...sr,...srk->...k", grad_roots.to(jac.dtype), jac).to(grad_roots.dtype)

    if not isinstance(p, torch.Tensor):
        raise TypeError(f"p must be a torch.Tensor, got {type(p).__name__}")
    return _Roots.apply(p)


def quadratic_roots(p, t_max: float = DEFAULT_T_MAX, max_derivative: float = DEFAULT_MAX_DERIVATIVE,
                    derivative: str = "mollified"):
    """Torch: roots of ``a t^2 + b t + c`` with the mollified implicit derivative as backward.

    Args:
        p: tensor (..., 3) ``[a, b, c]`` (float64 recommended).
        derivative: one of :data:`DERIVATIVES` ("orthogonal": eq. ``orthogonal_clamping_real_side``).

    Returns:
        tensor (..., 2, 2): ``[slot (t-, t+), (Re, Im)]``.
    """
    return _torch_roots(
        p,
        3,
        _quadratic_jacobian_raw,
        _check_positive(t_max, "t_max"),
        _check_positive(max_derivative, "max_derivative"),
        derivative,
    )


def cubic_roots(p, t_max: float = DEFAULT_T_MAX, max_derivative: float = DEFAULT_MAX_DERIVATIVE,
                derivative: str = "mollified"):
    """Torch: roots of ``q t^3 + a t^2 + b t + c`` with the mollified implicit derivative as backward.

    Args:
        p: tensor (..., 4) ``[q, a, b, c]``.
        derivative: one of :data:`DERIVATIVES` ("orthogonal": eq. ``orthogonal_clamping_real_side``).

    Returns:
        tensor (..., 3, 2): ``[slot (t-, tM, t+), (Re, Im)]``.
    """
    return _torch_roots(
        p, 4, _cubic_jacobian_raw, _check_positive(t_max, "t_max"), _check_positive(max_derivative, "max_derivative"),
        derivative,
    )
