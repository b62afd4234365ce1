"""Products and inverses of small matrices for code run under `jax.vmap` on CPU.

Batched by `vmap`, a product of two `6×6` matrices is a `dot_general` with tiny matrices
(a loop of tiny GEMM calls), and a `jnp.linalg.inv` of a `3×3` block a LAPACK `getrf`,
two `trsm` and a `while` loop for the pivots' permutation, per block. A matrix product
written as a sum over the contracted index, unrolled (each term an elementwise product of
a column and a row), and an elimination whose steps are elementwise are elementwise over
the batch, which XLA fuses into a few loops. A matrix–vector product stays a `dot`. Not a
broadcast product reduced over the contracted axis: such small reductions ran slowest.
With XLA's default multi-threaded Eigen (as users run it) a batched `dot_general` of `6×6`
blocks ran about 10× slower than single-threaded, and than the unrolled sum (figures:
`CHANGELOG.md`, RATTLE's joint products).

RATTLE's step on the chains of docs/articulated.md was the sum of such calls. The unrolled
products cost compile time instead (each is a kernel XLA compiles, where a `dot` is a
library call): they are used where a step runs them on every chain.
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp


def matvec(A, x):
    """`A x` over the last two axes of `A` `(..., p, q)` and the last of `x` `(..., q)`, a
    `dot`."""
    return jnp.einsum("...ij,...j->...i", A, x)


def matmul(A, B):
    """`A B` over the last two axes of `A` `(..., p, q)` and `B` `(..., q, r)`, the sum over
    `q` unrolled."""
    return _total(A[..., :, j, None] * B[..., None, j, :] for j in range(A.shape[-1]))


def transpose_matvec(A, x):
    """`Aᵀ x` over the last two axes of `A` `(..., q, p)` and the last of `x` `(..., q)`, a
    `dot`."""
    return jnp.einsum("...ji,...j->...i", A, x)


def _total(terms):
    """The sum of `terms` from the first (not from `0`: no addition of a zero array)."""
    return functools.reduce(operator.add, terms)


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
