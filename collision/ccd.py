"""Batched continuous collision detection (narrow phase) over the kernels of :mod:`kernels.ccd`.

Argument order follows ipctk: vertex-face ``(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1,
t2_t1)`` and edge-edge ``(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1)``; each
argument is an (N, 3) array of positions [m] (a single (3,) point is accepted as N = 1). The
motion over the step is linear, ``x(t) = x_t0 + t (x_t1 - x_t0)`` with ``t`` in ``[0, 1]``.

:func:`narrow_phase`, :func:`point_triangle_ccd` and :func:`edge_edge_ccd` take
``precision="float32"`` (the same narrow phase and root solver generated in float32 by
:mod:`kernels.variants`; positions are rounded to float32 before the kernel, times returned as
float64), ``tolerance_scale`` (a multiplier on the error bounds of the cubic's coefficients and of
the distances that decide a hit; default 1) and the root solver's knobs ``max_iterations`` /
``tolerance`` (see :func:`collision.roots.solve_cubic`). The defaults run the original kernels.

Example:
    >>> import numpy as np
    >>> from collision.ccd import point_triangle_ccd
    >>> tri = [np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])]
    >>> hit, toi = point_triangle_ccd(np.array([[0.2, 0.2, 1.0]]), *tri, np.array([[0.2, 0.2, -1.0]]), *tri)
    >>> bool(hit[0]), float(toi[0])
    (True, 0.5)
"""

from __future__ import annotations

import numpy as np
import warp as wp

from core.buffers import read_only
from collision.roots import DEFAULT_MAX_DERIVATIVE, DERIVATIVES, cubic_roots
from core.device import init_warp
from kernels import ccd as _k
from kernels import variants as _variants

__all__ = ["MeshCCDResult", "edge_edge_ccd", "edge_edge_roots", "mesh_ccd", "point_triangle_ccd", "point_triangle_roots"]

_DEVICE = "cpu"
_VF_NAMES = ("p_t0", "t0_t0", "t1_t0", "t2_t0", "p_t1", "t0_t1", "t1_t1", "t2_t1")
_EE_NAMES = ("ea0_t0", "ea1_t0", "eb0_t0", "eb1_t0", "ea0_t1", "ea1_t1", "eb0_t1", "eb1_t1")


def _stack(args, names) -> np.ndarray:
    """(N, 8, 3) float64 queries from eight (N, 3) arrays, with clear errors."""
    if len(args) != 8:
        raise TypeError(f"expected 8 position arrays ({', '.join(names)}), got {len(args)}")
    arrays = []
    n = None
    for name, a in zip(names, args):
        arr = np.asarray(a, dtype=np.float64) if not isinstance(a, np.ndarray) else a
        if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
            raise ValueError(f"{name}: expected real positions, got dtype {arr.dtype}")
        arr = np.asarray(arr, dtype=np.float64)
        if arr.ndim == 1:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"{name}: expected shape (N, 3), got {np.shape(a)}")
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise ValueError(f"{name}: has {arr.shape[0]} rows, but {names[0]} has {n}")
        bad = ~np.isfinite(arr)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ValueError(f"{name}: positions must be finite; {name}[{r}, {c}]={float(arr[r, c])!r} ({int(bad.sum())} bad entries)")
        arrays.append(arr)
    return np.ascontiguousarray(np.stack(arrays, axis=1))


_VARIANTS: dict = {}


def ccd_kernels(precision, tolerance_scale, max_iterations, tolerance):
    """:mod:`kernels.ccd` for the defaults, else its generated variant (cached here)."""
    if precision == "float64" and tolerance_scale == 1.0 and max_iterations is None and tolerance is None:
        return _k
    key = (precision, tolerance_scale, max_iterations, tolerance,
           type(tolerance_scale), type(max_iterations), type(tolerance))  # True != 1 here
    mod = _VARIANTS.get(key)
    if mod is None:
        init_warp()
        mod = _variants.kernel_variant(precision, max_iterations=max_iterations, tolerance=tolerance,
                                       tolerance_scale=tolerance_scale).ccd
        _VARIANTS[key] = mod
    return mod


def is_float32(k) -> bool:
    """Whether the narrow-phase kernels ``k`` (:func:`ccd_kernels`) are a float32 variant."""
    return k is not _k and k.mat83d._wp_scalar_type_ is wp.float32


def as_float32(values, name: str) -> np.ndarray:
    """``values`` (an array, contiguous, or a scalar) rounded to float32; a ValueError naming
    ``name`` if any overflows."""
    with np.errstate(over="ignore"):
        rounded = np.asarray(values, dtype=np.float32)
    if rounded.ndim:
        rounded = np.ascontiguousarray(rounded)
    if not np.isfinite(rounded).all():
        raise ValueError(f"{name} overflows float32 (precision='float32')")
    return rounded


def narrow_phase(kind: int, queries: np.ndarray, thickness: float = 0.0, *, precision: str = "float64",
                 tolerance_scale: float = 1.0, max_iterations=None, tolerance=None):
    """Batched narrow phase on stacked queries.

    Args:
        kind: 0 vertex-face, 1 edge-edge.
        queries: (N, 8, 3) float64: the four points at the start (rows 0-3, ipctk's order) and at
            the end (rows 4-7) of the step.
        thickness: minimum separation [m] (>= 0).
        precision: ``"float64"`` or ``"float32"`` (queries and thickness rounded to float32, the
            whole narrow phase and its root solver computed in float32).
        tolerance_scale: multiplier (> 0) of the coefficient and distance error bounds
            (``COEFFICIENT_ERROR_FACTOR``, ``DISTANCE_ERROR_FACTOR``): below 1 tighter (fewer
            false positives, false negatives possible), above 1 looser.
        max_iterations: the root solver's Newton-bisection iteration cap (None: 256).
        tolerance: the root solver's relative step tolerance (None: 2 ulp of the precision).

    Returns:
        (hit: bool (N,), toi: float64 (N,) fraction of the step, inf where no hit, source: int32
        (N,) where the time came from: 0 start, 1-3 cubic root slot, 4 collinear, 5 advancement,
        -1 none).

    Raises:
        ValueError: a bad thickness or knob (named), or (float32) positions that overflow float32.
    """
    k = ccd_kernels(precision, tolerance_scale, max_iterations, tolerance)
    t = float(thickness)
    if not np.isfinite(t) or t < 0.0:
        raise ValueError(f"thickness must be finite and >= 0, got {thickness!r}")
    init_warp()
    n = queries.shape[0]
    hit = np.zeros(n, dtype=np.int32)
    toi = np.full(n, np.inf)
    source = np.full(n, -1, dtype=np.int32)
    scalar, real = wp.float64, np.float64
    if is_float32(k):
        scalar, real = wp.float32, np.float32
        queries = as_float32(queries, "queries")
        as_float32(t, "thickness")
        toi = np.full(n, np.inf, dtype=np.float32)
    if n:
        wp.launch(
            k.ccd_kernel,
            dim=n,
            inputs=[kind, wp.array(queries, dtype=k.mat83d, device=_DEVICE, copy=False), scalar(t)],
            outputs=[
                wp.array(hit, dtype=wp.int32, device=_DEVICE, copy=False),
                wp.array(toi, dtype=scalar, device=_DEVICE, copy=False),
                wp.array(source, dtype=wp.int32, device=_DEVICE, copy=False),
            ],
            device=_DEVICE,
        )
        wp.synchronize_device(_DEVICE)
    if real is np.float32:
        toi = toi.astype(np.float64)
    return hit.astype(bool), toi, source

ONES3 = read_only(np.ones(3))[0]
"""Row sums of (N, 3) arrays as a product ``a @ ONES3`` (``einsum`` parses its subscripts on every call)."""


def point_triangle_ccd(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1, thickness: float = 0.0, *,
                       precision: str = "float64", tolerance_scale: float = 1.0, max_iterations=None, tolerance=None):
    """Does the vertex hit the triangle during the step, and when first?

    Args:
        p_t0: the vertex at the start of the step [m], (N, 3).
        t0_t0: the triangle's first corner at the start [m], (N, 3).
        t1_t0: its second corner at the start [m], (N, 3).
        t2_t0: its third corner at the start [m], (N, 3).
        p_t1: the vertex at the end of the step [m], (N, 3).
        t0_t1: the first corner at the end [m], (N, 3).
        t1_t1: the second corner at the end [m], (N, 3).
        t2_t1: the third corner at the end [m], (N, 3).
        thickness: minimum separation [m] (>= 0); contact when the distance reaches it.
        precision: see :func:`narrow_phase` (default: the float64 kernels as written).
        tolerance_scale: see :func:`narrow_phase`.
        max_iterations: see :func:`narrow_phase`.
        tolerance: see :func:`narrow_phase`.

    Returns:
        (hit: bool (N,), toi: float64 (N,) earliest time of impact in [0, 1], ``inf`` where no hit).

    Raises:
        ValueError: wrong shapes, mismatched lengths, non-finite positions, a bad thickness or
            knob (named).
    """
    queries = _stack((p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1), _VF_NAMES)
    hit, toi, _ = narrow_phase(0, queries, thickness, precision=precision, tolerance_scale=tolerance_scale,
                               max_iterations=max_iterations, tolerance=tolerance)
    return hit, toi


def edge_edge_ccd(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1, thickness: float = 0.0, *,
                  precision: str = "float64", tolerance_scale: float = 1.0, max_iterations=None, tolerance=None):
    """Do the two edges hit during the step, and when first?

    Args:
        ea0_t0: edge a's first endpoint at the start of the step [m], (N, 3).
        ea1_t0: edge a's second endpoint at the start [m], (N, 3).
        eb0_t0: edge b's first endpoint at the start [m], (N, 3).
        eb1_t0: edge b's second endpoint at the start [m], (N, 3).
        ea0_t1: edge a's first endpoint at the end of the step [m], (N, 3).
        ea1_t1: edge a's second endpoint at the end [m], (N, 3).
        eb0_t1: edge b's first endpoint at the end [m], (N, 3).
        eb1_t1: edge b's second endpoint at the end [m], (N, 3).
        thickness: minimum separation [m] (>= 0).
        precision: see :func:`narrow_phase`.
        tolerance_scale: see :func:`narrow_phase`.
        max_iterations: see :func:`narrow_phase`.
        tolerance: see :func:`narrow_phase`.

    Returns:
        (hit: bool (N,), toi: float64 (N,) in [0, 1], ``inf`` where no hit).
    """
    queries = _stack((ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1), _EE_NAMES)
    hit, toi, _ = narrow_phase(1, queries, thickness, precision=precision, tolerance_scale=tolerance_scale,
                               max_iterations=max_iterations, tolerance=tolerance)
    return hit, toi


def _roots(kind: int, queries: np.ndarray, max_derivative: float):
    init_warp()
    hit, toi, source = narrow_phase(kind, queries, 0.0)
    n = queries.shape[0]
    roots = np.zeros((n, 6))
    out_toi = np.zeros(n)
    if n:
        wp.launch(
            _k.ccd_time_of_impact_kernel,
            dim=n,
            inputs=[
                wp.array(queries, dtype=_k.mat83d, device=_DEVICE, copy=False),
                wp.array(source, dtype=wp.int32, device=_DEVICE, copy=False),
                wp.array(np.where(hit, toi, np.inf), dtype=wp.float64, device=_DEVICE),
                wp.float64(max_derivative),
            ],
            outputs=[
                wp.array(out_toi, dtype=wp.float64, device=_DEVICE, copy=False),
                wp.array(roots, dtype=_k.vec6d, device=_DEVICE, copy=False),
            ],
            device=_DEVICE,
        )
        wp.synchronize_device(_DEVICE)
    return roots.reshape(n, 6).view(np.complex128)


def point_triangle_roots(p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1, max_derivative: float = DEFAULT_MAX_DERIVATIVE):
    """All three (complex) roots of each query's coplanarity cubic, slots (t-, tM, t+).

    The "lifted" event: when the vertex misses, the roots it would need are complex, and an
    optimiser can aim at them (their derivatives come from :mod:`kernels.roots`).
    """
    queries = _stack((p_t0, t0_t0, t1_t0, t2_t0, p_t1, t0_t1, t1_t1, t2_t1), _VF_NAMES)
    return _roots(0, queries, max_derivative)


def edge_edge_roots(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1, max_derivative: float = DEFAULT_MAX_DERIVATIVE):
    """All three (complex) roots of each edge-edge query's coplanarity cubic."""
    queries = _stack((ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1), _EE_NAMES)
    return _roots(1, queries, max_derivative)


def _taped_query_function(kernel, out_dtype, out_shape):
    """A torch.autograd.Function over Warp ``kernel(queries (N, 8, 3), *scalars) -> out (N,)``:
    forward runs it under a ``wp.Tape``, backward replays the tape (the kernels' custom adjoints,
    e.g. the mollified root derivative). ``out_shape``: the torch shape of one output row."""
    import torch

    class Function(torch.autograd.Function):
        @staticmethod
        def forward(ctx, queries, *scalars):
            init_warp()
            n = queries.shape[0]
            q = wp.array(queries.detach().cpu().numpy().reshape(n, 8, 3), dtype=_k.mat83d, device=_DEVICE,
                         requires_grad=True)
            out = wp.zeros(n, dtype=out_dtype, device=_DEVICE, requires_grad=True)
            tape = wp.Tape()
            with tape:
                wp.launch(kernel, dim=n, inputs=[q, *(wp.float64(x) for x in scalars)], outputs=[out],
                          device=_DEVICE)
            ctx.tape, ctx.q, ctx.out, ctx.device = tape, q, out, queries.device
            return torch.from_numpy(out.numpy().reshape((n, *out_shape)).copy()).to(queries.device)

        @staticmethod
        def backward(ctx, grad):
            n = ctx.q.shape[0]
            ctx.out.grad.assign(wp.array(grad.detach().cpu().numpy().reshape(n, -1).astype(np.float64),
                                         dtype=out_dtype, device=_DEVICE))
            ctx.tape.backward()
            result = torch.from_numpy(ctx.q.grad.numpy().reshape(n, 8, 3).copy()).to(ctx.device)
            ctx.tape.zero()
            return (result, *([None] * (len(ctx.needs_input_grad) - 1)))

    return Function


class _CoplanarityRoots:
    """The torch functions of the coplanarity cubic (built lazily: torch stays optional for the
    numpy API): its three roots with the kernels' mollified adjoint, and its unit-scaled
    coefficients (for a root derivative chosen outside the kernels)."""

    function = None
    coefficients_function = None

    @classmethod
    def get(cls):
        if cls.function is None:
            cls.function = _taped_query_function(_k.coplanarity_roots_kernel, _k.vec6d, (3, 2))
        return cls.function

    @classmethod
    def get_coefficients(cls):
        if cls.coefficients_function is None:
            cls.coefficients_function = _taped_query_function(_k.coplanarity_coefficients_kernel, wp.vec4d, (4,))
        return cls.coefficients_function


def coplanarity_roots(x_start, x_end, max_derivative: float = DEFAULT_MAX_DERIVATIVE, derivative: str = "mollified"):
    """Torch: the lifted events of vertex-face or edge-edge pairs moving linearly over a step.

    The roots (real or complex) of the coplanarity cubic of the four points' straight paths
    ``x(s) = x_start + s (x_end - x_start)``, ``s`` the fraction of the step: a hit is a real root
    in [0, 1] with the point inside the triangle (edges overlapping); a miss has the wanted root
    complex or outside. Backward is the mollified implicit derivative (:mod:`kernels.roots`,
    bounded by ``max_derivative`` for the cubic scaled to a largest coefficient of 1), so a loss
    on a complex root has a finite gradient that pulls it onto the real axis.

    Args:
        x_start: torch float64 (N, 4, 3) [m]: vertex and triangle corners (vertex-face) or the
            two edges' endpoints (edge-edge) at the start of the step.
        x_end: the same four points at the end of the step, torch float64 (N, 4, 3) [m].
        max_derivative: the robust-division bound ``M`` (> 0).
        derivative: "mollified" (the kernels' robust division) or "orthogonal" (real roots: the
            exact derivative with only its part along the merging direction clamped to ``M``,
            eq. ``orthogonal_clamping_real_side``; :func:`collision.roots.orthogonal_clamped_jacobian`).

    Returns:
        torch float64 (N, 3, 2): slots (t-, tM, t+) of design.md, (Re, Im), in fractions of the step.

    Raises:
        ValueError: not float64 tensors of matching (N, 4, 3) shape, or non-finite positions.
    """
    import torch

    for name, x in (("x_start", x_start), ("x_end", x_end)):
        if not isinstance(x, torch.Tensor) or x.dtype != torch.float64:
            raise ValueError(f"{name} must be a float64 torch tensor of shape (N, 4, 3)")
        if x.ndim != 3 or tuple(x.shape[1:]) != (4, 3):
            raise ValueError(f"{name} must have shape (N, 4, 3), got {tuple(x.shape)}")
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"{name} must be finite (it holds NaN or inf)")
    if x_start.shape != x_end.shape:
        raise ValueError(f"x_start and x_end must have the same shape, got {tuple(x_start.shape)} and {tuple(x_end.shape)}")
    if not float(max_derivative) > 0.0:
        raise ValueError(f"max_derivative must be positive, got {max_derivative!r}")
    if derivative not in DERIVATIVES:
        raise ValueError(f"derivative must be one of {DERIVATIVES}, got {derivative!r}")
    queries = torch.cat([x_start, x_end], dim=1)
    if queries.shape[0] == 0:
        return torch.zeros((0, 3, 2), dtype=torch.float64, device=queries.device)
    if derivative == "orthogonal":
        coefficients = _CoplanarityRoots.get_coefficients().apply(queries)
        return cubic_roots(coefficients, float(_k.CCD_T_MAX), float(max_derivative), derivative="orthogonal")
    return _CoplanarityRoots.get().apply(queries, float(max_derivative))


# ---------------------------------------------------------------------------------------------
# meshes: broad phase + narrow phase
# ---------------------------------------------------------------------------------------------


class MeshCCDResult:
    """Contacts of one step of triangle meshes (all arrays are numpy).

    Attributes:
        vf: (K, 2) int64 candidate [vertex, face] pairs from the broad phase.
        vf_hit, vf_toi: (K,) their narrow-phase results (toi ``inf`` where no hit).
        ee: (L, 2) int64 candidate [edge_a, edge_b] pairs (indices into ``edges``).
        ee_hit, ee_toi: (L,) their results.
        edges: (E, 2) the edge list the ``ee`` indices refer to.
        time_of_impact: earliest time of impact over all pairs in [0, 1] (``inf`` if none).
    """

    def __init__(self, vf, vf_hit, vf_toi, ee, ee_hit, ee_toi, edges):
        self.vf, self.vf_hit, self.vf_toi = vf, vf_hit, vf_toi
        self.ee, self.ee_hit, self.ee_toi = ee, ee_hit, ee_toi
        self.edges = edges
        tois = np.concatenate([vf_toi[vf_hit], ee_toi[ee_hit]])
        self.time_of_impact = float(tois.min()) if tois.size else float("inf")

    @property
    def num_contacts(self) -> int:
        return int(self.vf_hit.sum() + self.ee_hit.sum())

    def __repr__(self) -> str:
        return (
            f"MeshCCDResult(vf candidates={len(self.vf)}, ee candidates={len(self.ee)}, "
            f"contacts={self.num_contacts}, time_of_impact={self.time_of_impact})"
        )


def mesh_ccd(x0, x1, faces, edges=None, *, thickness: float = 0.0, broad_phase=None, **broad_phase_options) -> MeshCCDResult:
    """Continuous collision detection of triangle meshes over one step.

    Swept-box broad phase (:mod:`collision.broad_phase`, adjacency excluded, body rules via
    ``groups``/``self_collision``/``static``) followed by the batched narrow phase on every
    candidate vertex-face and edge-edge pair.

    Args:
        x0: (V, 3) vertex positions [m] at the start of the step.
        x1: (V, 3) vertex positions [m] at the end of the step.
        faces: (F, 3) triangle vertex indices.
        edges: (E, 2) edge vertex indices; derived from ``faces`` when None.
        thickness: minimum separation [m] (>= 0), also the broad phase's inflation.
        broad_phase: optional :class:`collision.broad_phase.BroadPhase` built for this topology
            (reused between steps); otherwise :func:`collision.broad_phase.candidate_pairs` runs.
        **broad_phase_options: ``groups``, ``self_collision``, ``static`` for candidate_pairs.

    Returns:
        :class:`MeshCCDResult` with per-pair hits and times and the earliest time of impact.
    """
    from collision.broad_phase import candidate_pairs, mesh_edges

    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    x1 = np.ascontiguousarray(x1, dtype=np.float64)
    faces_arr = np.asarray(faces)
    edge_arr = mesh_edges(faces_arr) if edges is None else np.asarray(edges)
    if broad_phase is not None:
        vf, ee = broad_phase.query(x0, x1, thickness)
    else:
        vf, ee = candidate_pairs(x0, x1, faces_arr, edge_arr, inflation=thickness, **broad_phase_options)
    # gather (N, 8, 3) queries: rows 0-3 at t0, rows 4-7 at t1
    vf_idx = np.column_stack([vf[:, 0], faces_arr[vf[:, 1]]]) if len(vf) else np.zeros((0, 4), dtype=np.int64)
    ee_idx = np.column_stack([edge_arr[ee[:, 0]], edge_arr[ee[:, 1]]]) if len(ee) else np.zeros((0, 4), dtype=np.int64)
    vf_q = np.ascontiguousarray(np.concatenate([x0[vf_idx], x1[vf_idx]], axis=1))
    ee_q = np.ascontiguousarray(np.concatenate([x0[ee_idx], x1[ee_idx]], axis=1))
    vf_hit, vf_toi, _ = narrow_phase(0, vf_q, thickness)
    ee_hit, ee_toi, _ = narrow_phase(1, ee_q, thickness)
    return MeshCCDResult(vf, vf_hit, vf_toi, ee, ee_hit, ee_toi, edge_arr)
