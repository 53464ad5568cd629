"""Dense LU solves of the contact systems (Warp, float64): factor, substitute, and the adjoint
solve with the transposed matrix (implicit differentiation of the impulse solve).
"""

import warp as wp



@wp.func
def lu_factor(work: wp.array2d(dtype=wp.float64), pivots: wp.array(dtype=wp.int32)):
    """In-place LU factorisation of the square ``work`` by Gaussian elimination with partial
    pivoting (whole rows swapped, as LAPACK's getrf): the unit lower factor's multipliers below
    the diagonal, the upper factor on and above it, the row swapped with row ``k`` at step ``k``
    in ``pivots[k]``. A zero column leaves a zero pivot (its unknown is set to 0 by
    :func:`lu_substitute`)."""
    n = work.shape[0]
    for k in range(n):
        p = k
        best = wp.abs(work[k, k])
        for i in range(k + 1, n):
            if wp.abs(work[i, k]) > best:
                best = wp.abs(work[i, k])
                p = i
        pivots[k] = p
        if p != k:
            for j in range(n):
                tmp = work[k, j]
                work[k, j] = work[p, j]
                work[p, j] = tmp
        pivot = work[k, k]
        if pivot != wp.float64(0.0):
            for i in range(k + 1, n):
                f = work[i, k] / pivot
                work[i, k] = f
                if f != wp.float64(0.0):
                    for j in range(k + 1, n):
                        work[i, j] = work[i, j] - f * work[k, j]


@wp.func
def lu_substitute(work: wp.array2d(dtype=wp.float64), pivots: wp.array(dtype=wp.int32),
                  solution: wp.array(dtype=wp.float64)):
    """``solution`` (holding the right-hand side) overwritten by the solution of the system
    factorised by :func:`lu_factor`: the row swaps, then forward and back substitution."""
    n = work.shape[0]
    for k in range(n):
        p = pivots[k]
        if p != k:
            tmp = solution[k]
            solution[k] = solution[p]
            solution[p] = tmp
    for i in range(n):
        s = solution[i]
        for j in range(i):
            s = s - work[i, j] * solution[j]
        solution[i] = s
    for kk in range(n):
        k = n - 1 - kk
        s = solution[k]
        for j in range(k + 1, n):
            s = s - work[k, j] * solution[j]
        if work[k, k] != wp.float64(0.0):
            solution[k] = s / work[k, k]
        else:
            solution[k] = wp.float64(0.0)


@wp.kernel(enable_backward=False)
def lu_factor_kernel(
    matrix: wp.array2d(dtype=wp.float64),
    transpose: int,
    work: wp.array2d(dtype=wp.float64),
    pivots: wp.array(dtype=wp.int32),
):
    """:func:`lu_factor` of ``matrix`` (of its transpose when ``transpose``) into ``work`` and
    ``pivots``, launched with ``dim=1``."""
    n = matrix.shape[0]
    for i in range(n):
        for j in range(n):
            if transpose != 0:
                work[i, j] = matrix[j, i]
            else:
                work[i, j] = matrix[i, j]
    lu_factor(work, pivots)


@wp.kernel(enable_backward=False)
def lu_solve_kernel(
    work: wp.array2d(dtype=wp.float64),
    pivots: wp.array(dtype=wp.int32),
    rhs: wp.array(dtype=wp.float64),
    solution: wp.array(dtype=wp.float64),
):
    """``solution = A^-1 rhs`` from the factors of :func:`lu_factor_kernel`, launched with
    ``dim=1``. Not differentiated by the tape: the caller records the implicit adjoint (a solve
    with the transposed matrix) instead."""
    for i in range(rhs.shape[0]):
        solution[i] = rhs[i]
    lu_substitute(work, pivots, solution)


@wp.kernel
def solve_adjoint_kernel(
    adjoint: wp.array(dtype=wp.float64),
    solution: wp.array(dtype=wp.float64),
    matrix_grad: wp.array2d(dtype=wp.float64),
    rhs_grad: wp.array(dtype=wp.float64),
):
    """Implicit adjoint of ``x = A^-1 b`` given ``mu = A^-T x_bar``: ``b_bar += mu``,
    ``A_bar -= mu x^T`` (launched over (n, n))."""
    r, u = wp.tid()
    matrix_grad[r, u] = matrix_grad[r, u] - adjoint[r] * solution[u]
    if u == 0:
        rhs_grad[r] = rhs_grad[r] + adjoint[r]
