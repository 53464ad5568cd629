"""The solver's adjoint inside Warp kernels: ``@wp.func_grad`` under a ``wp.Tape``.

A kernel that calls :func:`kernels.roots.cubic_roots` / :func:`kernels.roots.quadratic_roots` and
reduces the roots with fixed weights must backpropagate exactly ``weights @ Jacobian`` (the
mollified Jacobian of the numpy API, itself checked against mpmath finite differences in
``test_roots_derivatives.py``), including at degenerate inputs where differentiating the
iterations would give garbage: a triple root, ``q = 0``, the all-zero polynomial.
"""

import numpy as np
import warp as wp

from collision.roots import cubic_root_jacobian, quadratic_root_jacobian
from kernels.roots import cubic_roots, quadratic_roots, vec6d

wp.init()


@wp.kernel
def _weighted_cubic_roots(p: wp.array(dtype=wp.vec4d), w: wp.array(dtype=vec6d), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    r = cubic_roots(p[i], wp.float64(1.0e150), wp.float64(1000.0))
    out[i] = wp.dot(r, w[i])


@wp.kernel
def _weighted_quadratic_roots(
    p: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec4d), out: wp.array(dtype=wp.float64)
):
    i = wp.tid()
    r = quadratic_roots(p[i], wp.float64(1.0e150), wp.float64(1000.0))
    out[i] = wp.dot(r, w[i])


def _tape_gradient(kernel, coefficients, weights, coef_type, weight_type):
    n = len(coefficients)
    p = wp.array(coefficients, dtype=coef_type, requires_grad=True)
    w = wp.array(weights, dtype=weight_type)
    out = wp.zeros(n, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(kernel, dim=n, inputs=[p, w], outputs=[out])
    tape.backward(grads={out: wp.ones(n, dtype=wp.float64)})
    return p.grad.numpy()


def test_cubic_adjoint_is_the_mollified_jacobian():
    rng = np.random.default_rng(3)
    coefficients = np.concatenate(
        [
            rng.uniform(-2, 2, (64, 4)),
            [[1, 0, 0, 0], [0, 1, 0, -1], [0, -1, 0, 1], [0, 0, 0, 0], [0, 0, -7.1, 6], [1, -1, 0.25, 0]],
        ]
    )
    weights = rng.normal(size=(len(coefficients), 6))
    grad = _tape_gradient(_weighted_cubic_roots, coefficients, weights, wp.vec4d, vec6d)
    jac = cubic_root_jacobian(coefficients)
    expected = np.einsum("nsr,nsrk->nk", weights.reshape(-1, 3, 2), jac)
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(grad, expected, rtol=1e-14, atol=1e-300)
    # degenerate rows really exercise the clamp: [1, 0, 0, 0] has dt/dc = -M for the real slots
    assert np.abs(jac[-6]).max() == 1000.0


def test_quadratic_adjoint_is_the_mollified_jacobian():
    rng = np.random.default_rng(4)
    coefficients = np.concatenate([rng.uniform(-2, 2, (64, 3)), [[0, -5.1, 5], [0, 0, 5], [0, 0, 0], [1, -1, 0.25]]])
    weights = rng.normal(size=(len(coefficients), 4))
    grad = _tape_gradient(_weighted_quadratic_roots, coefficients, weights, wp.vec3d, wp.vec4d)
    jac = quadratic_root_jacobian(coefficients)
    expected = np.einsum("nsr,nsrk->nk", weights.reshape(-1, 2, 2), jac)
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(grad, expected, rtol=1e-14, atol=1e-300)
