"""Solves with a matrix whose blocks follow the joints of a tree: block LU without fill.

The joints' Gram matrix `C M⁻¹ Cᵀ` (the velocity projection) and RATTLE's Schur
complement `B A⁻¹ Cᵀ` (`≈ h C M⁻¹ Cᵀ`) have a block `(a, b)` only where joints `a` and
`b` share a body: a chain's are block tridiagonal. Eliminating the joints leaves first
(deepest child first) creates no fill: the joints still coupled to a leaf's joint all
touch its parent body, so they are coupled already. The factorisation is then `N` small
diagonal-block inverses (3×3 ball, 5×5 hinge) and products of small blocks, where the
dense `c × c` inverse (one LAPACK call per matrix of the batch) was the largest part of
the projection and of the iteration's set-up for a 5-link hinge chain.

No pivoting across blocks: every pivot block is a Schur complement of a symmetric
positive definite matrix (the Gram matrix), or of one perturbed by O(|ξ|) (RATTLE's),
so it stays nonsingular and well conditioned for steps the iteration converges at, and
each small block is inverted by elimination in order (`_small_linalg.inverse`):
under `jax.vmap` a LAPACK inverse per block (`getrf`, two `trsm` and a loop for the
pivots) cost more than the elimination itself.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._small_linalg import inverse as small_inverse
from .._small_linalg import matmul


def tree_structure(parents, sizes):
    """`(slices, order, neighbours)` for joints `sizes` (a size per body, 0 without a
    joint) of the tree `parents`: each joint's rows, the elimination order (deepest first)
    and, for each joint, the joints that share a body with it."""
    offsets, start = {}, 0
    for i, size in enumerate(sizes):
        if size:
            offsets[i] = slice(start, start + size)
            start += size
    joints = list(offsets)

    def touches(i):
        return {i} if parents[i] == -1 else {i, parents[i]}

    def depth(i):
        return 0 if parents[i] == -1 else 1 + depth(parents[i])

    neighbours = {a: [b for b in joints if b != a and touches(a) & touches(b)] for a in joints}
    order = sorted(joints, key=lambda i: -depth(i))
    return offsets, order, neighbours


def tree_solver(S, structure):
    """`r ↦ S⁻¹ r` for `S` `(c, c)` with the block pattern of `structure`
    (`tree_structure`), factored here once; `r` `(c,)` or `(c, k)`."""
    offsets, order, neighbours = structure
    blocks = {(a, b): S[offsets[a], offsets[b]] for a in order for b in [a, *neighbours[a]]}
    return block_tree_solver(blocks, structure)


def block_tree_solver(blocks, structure):
    """`tree_solver` from the nonzero blocks `{(a, b): S_ab}` of `S` alone (joints named
    by their body, `b` = `a` or one of its `neighbours`), as `JointRows.gram_blocks`
    gives them: the dense `S` is never formed."""
    offsets, order, neighbours = structure
    block = dict(blocks)
    inverse, lower, done = {}, {}, set()
    for a in order:
        inverse[a] = small_inverse(block[a, a])
        rest = [b for b in neighbours[a] if b not in done]
        for b in rest:
            lower[b, a] = matmul(block[b, a], inverse[a])
        for b in rest:
            for d in rest:
                block[b, d] = block[b, d] - matmul(lower[b, a], block[a, d])
        done.add(a)

    def solve(r):
        parts = {a: r[offsets[a]] for a in order}
        eliminated = set()
        for a in order:
            for b in neighbours[a]:
                if b not in eliminated and b != a:
                    if (b, a) in lower:
                        parts[b] = parts[b] - lower[b, a] @ parts[a]
            eliminated.add(a)
        x, later = {}, set()
        for a in reversed(order):
            value = parts[a]
            for b in neighbours[a]:
                if b in later:
                    value = value - block[a, b] @ x[b]
            x[a] = inverse[a] @ value
            later.add(a)
        return jnp.concatenate([x[a] for a in sorted(offsets)])

    return solve
