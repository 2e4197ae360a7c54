"""Linear solves of the few-by-few symmetric positive definite systems a filter step
makes at every sample, in a handful of fused elementwise kernels.

``jnp.linalg.solve`` on a 2 x 2 or 4 x 4 matrix calls LAPACK's LU (``getrf``), two
triangular solves and a ``while`` loop turning pivots into a permutation: on XLA's CPU
runtime each of those is a separate thunk, and a deployed policy's step of one sample
spent more in them than in its network (``results/bench/deploy.json``). Gauss-Jordan
elimination unrolled over the ``n`` pivots is ``n`` whole-array updates of the
augmented matrix ``[A | B]``, each one fusion. Without pivoting it needs a matrix whose
leading minors are well away from zero: a symmetric positive definite one (the
innovation covariance ``H P H^T + R``, a covariance block, ``J^T J + lambda I``), the
only kind the callers pass. Larger systems keep LAPACK (Cholesky), where the thunks'
fixed cost no longer dominates. Golub & Van Loan, "Matrix Computations" (4th ed.),
§3.1 and §4.2 (no pivoting needed for a positive definite matrix).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve

from jaxcal.typedefs import Array

# up to this size the unrolled elimination (n fused updates) is cheaper per call than
# LAPACK's factor-and-solve; above it the program's size grows as n kernels anyway
UNROLL_MAX = 8


def spd_solve(a: Array, b: Array) -> Array:
    """``a^-1 b`` for a symmetric positive definite ``a`` ``[n, n]`` and ``b`` ``[n]``
    or ``[n, m]`` (jittable, differentiable; the shape of ``b`` is returned)."""
    n = a.shape[-1]
    if a.shape != (n, n) or b.shape[0] != n:
        raise ValueError(
            f"spd_solve: a {a.shape} must be square and b {b.shape} [n, ...]"
        )
    if n > UNROLL_MAX:
        return cho_solve(cho_factor(a, lower=True), b)
    vector = b.ndim == 1
    aug = jnp.concatenate([a, b[:, None] if vector else b], axis=1)
    rows = jnp.arange(n)[:, None]
    for k in range(n):  # static: n fused updates
        pivot_row = aug[k] / aug[k, k]
        aug = jnp.where(rows == k, pivot_row, aug - aug[:, k : k + 1] * pivot_row)
    out = aug[:, n:]
    return out[:, 0] if vector else out
