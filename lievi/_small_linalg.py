"""Products and inverses of small matrices written elementwise, for code run under
`jax.vmap` on CPU.

Batched by `vmap`, a `6×6` product or a `jnp.linalg.inv` of a `3×3` block is a
`dot_general` with tiny matrices (a loop of tiny GEMM calls) or a LAPACK `getrf`, two
`trsm` and a `while` loop for the pivots' permutation, per block. Written as
broadcast-multiply-and-sum and an elimination whose steps are elementwise, the same
arithmetic is elementwise over the batch, which XLA fuses into a few loops: RATTLE's step
on the chains of docs/articulated.md was the sum of such calls.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def matvec(A, x):
    """`A x` over the last two axes of `A` `(..., p, q)` and the last of `x` `(..., q)`."""
    return jnp.sum(A * x[..., None, :], axis=-1)


def inverse(A):
    """`A⁻¹` for `A` `(..., n, n)` by Gauss–Jordan elimination without pivoting, a
    `lax.fori_loop` over the pivots, each step elementwise over the whole batch.

    For the blocks it is used on — a body's kinetic tensor over `h` plus an `O(|ξ|)`
    perturbation, and the pivot blocks of a kinetic-metric Gram matrix, Schur complements
    of symmetric positive definite matrices — the diagonal pivots are the large entries,
    so elimination in order is stable, as Cholesky's is; the iterations that use these
    inverses evaluate their exact residuals, so rounding here moves how fast they
    converge, not where.

    In a loop, not unrolled: the `n²` entries of each of the `n` steps unrolled were
    hundreds of kernels of their own in a compiled RATTLE step (each a module XLA's CPU
    backend compiles separately); looped, the program is smaller and the step no
    slower."""
    n = A.shape[-1]
    index = jnp.arange(n)

    def eliminate(k, a):
        row = jax.lax.dynamic_index_in_dim(a, k, axis=-2, keepdims=False)
        pivot = 1 / jax.lax.dynamic_index_in_dim(row, k, axis=-1, keepdims=False)
        is_k = index == k
        # Row `k` scaled by the pivot (its entry `k` the pivot itself); every other row
        # `i` less `a_ik` times it (its entry `k` then `−a_ik·pivot`).
        row = jnp.where(is_k, pivot[..., None], row * pivot[..., None])
        factor = jax.lax.dynamic_index_in_dim(a, k, axis=-1, keepdims=False)[..., :, None]
        others = jnp.where(is_k, -factor * pivot[..., None, None], a - factor * row[..., None, :])
        return jnp.where(is_k[:, None], row[..., None, :], others)

    return jax.lax.fori_loop(0, n, eliminate, A)
