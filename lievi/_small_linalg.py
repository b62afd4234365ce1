"""Products and inverses of small matrices written elementwise, for code run under
`jax.vmap` on CPU.

Batched by `vmap`, a `6×6` product or a `jnp.linalg.inv` of a `3×3` block is a
`dot_general` with tiny matrices (a loop of tiny GEMM calls) or a LAPACK `getrf`, two
`trsm` and a `while` loop for the pivots' permutation, per block. Written as
broadcast-multiply-and-sum and an unrolled elimination, the same arithmetic is
elementwise over the batch, which XLA fuses into a few loops: RATTLE's step on the
chains of docs/articulated.md was the sum of such calls.
"""

from __future__ import annotations

import jax.numpy as jnp


def matvec(A, x):
    """`A x` over the last two axes of `A` `(..., p, q)` and the last of `x` `(..., q)`."""
    return jnp.sum(A * x[..., None, :], axis=-1)


def inverse(A):
    """`A⁻¹` for `A` `(..., n, n)` by Gauss–Jordan elimination without pivoting, unrolled.

    For the blocks it is used on — a body's kinetic tensor over `h` plus an `O(|ξ|)`
    perturbation, and the pivot blocks of a kinetic-metric Gram matrix, Schur complements
    of symmetric positive definite matrices — the diagonal pivots are the large entries,
    so elimination in order is stable, as Cholesky's is; the iterations that use these
    inverses evaluate their exact residuals, so rounding here moves how fast they
    converge, not where."""
    n = A.shape[-1]
    a = [[A[..., i, j] for j in range(n)] for i in range(n)]
    for k in range(n):
        pivot = 1 / a[k][k]
        a[k] = [pivot if j == k else a[k][j] * pivot for j in range(n)]
        for i in range(n):
            if i == k:
                continue
            factor = a[i][k]
            a[i] = [-factor * pivot if j == k else a[i][j] - factor * a[k][j] for j in range(n)]
    return jnp.stack([jnp.stack(row, axis=-1) for row in a], axis=-2)
