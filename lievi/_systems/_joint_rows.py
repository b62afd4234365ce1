"""A constraint-shaped matrix `(c, N, 6)` kept by joint: each joint's rows touch two bodies.

A joint constrains its body and its parent (or the world) only, so of the constraint
Jacobian `C` `(c, N, 6)` each joint's rows are nonzero in two columns of bodies at most.
Products with `C` as a dense array — `Cᵀλ`, `C v`, the Gram matrix `C W Cᵀ` — spent
almost all their arithmetic on those zeros: under `jax.vmap` the Gram matrix of a 5-link
hinge chain, a `(25, 30)·(30, 25)` product per chain, and its solve were a third of a
`lievi.RATTLE` step. Kept by joint, `Cᵀλ` is a sum of two blocks per body, `C v` two
products per joint and the Gram matrix only the blocks where two joints share a body,
the pattern `tree_solver` factors.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._small_linalg import matmul, matvec, transpose_matvec


class JointRows(eqx.Module):
    """The rows of a `(c, N, 6)` matrix by joint, in body order: joint `k` between body
    `child[k]` and `parent[k]` (`-1`: the world, no columns) has rows `of_parent[k]` and
    `of_child[k]`, each `(size_k, 6)`. A pytree (its rows the leaves), so that a step can
    hand the rows of its end to the next step (`lievi.RATTLE`'s step cache)."""

    n_bodies: int = eqx.field(static=True)
    child: tuple[int, ...] = eqx.field(static=True)
    parent: tuple[int, ...] = eqx.field(static=True)
    of_parent: list
    of_child: list

    def __init__(self, n_bodies, child, parent, of_parent, of_child):
        self.n_bodies = n_bodies
        self.child, self.parent = tuple(child), tuple(parent)
        self.of_parent, self.of_child = list(of_parent), list(of_child)

    @property
    def n_rows(self) -> int:
        """`c`, the rows of all joints."""
        return sum(rows.shape[0] for rows in self.of_child)

    def _columns(self, k):
        """`(body, rows)` of joint `k`'s nonzero column blocks."""
        columns = [(self.child[k], self.of_child[k])]
        if self.parent[k] != -1:
            columns.append((self.parent[k], self.of_parent[k]))
        return columns

    def times_blocks(self, W):
        """`C W` for a block-diagonal `W` `(N, 6, 6)`: each column block times its body's."""
        of_parent = [
            rows if p == -1 else matmul(rows, W[p]) for p, rows in zip(self.parent, self.of_parent)
        ]
        of_child = [matmul(rows, W[i]) for i, rows in zip(self.child, self.of_child)]
        return JointRows(self.n_bodies, self.child, self.parent, of_parent, of_child)

    def apply(self, v):
        """`C v` `(c,)` for `v` `(N, 6)`."""
        parts = []
        for k in range(len(self.child)):
            parts.append(sum(matvec(rows, v[j]) for j, rows in self._columns(k)))
        return jnp.concatenate(parts)

    def transpose_apply(self, impulse):
        """`Cᵀ λ` `(N, 6)` for `λ` `(c,)`: each body's sum over the joints touching it."""
        per_body = [[] for _ in range(self.n_bodies)]
        start = 0
        for k in range(len(self.child)):
            size = self.of_child[k].shape[0]
            part = impulse[start : start + size]
            start += size
            for j, rows in self._columns(k):
                per_body[j].append(transpose_matvec(rows, part))
        zero = jnp.zeros((6,), impulse.dtype)
        return jnp.stack([sum(terms) if terms else zero for terms in per_body])

    def gram_blocks(self, W, other, structure):
        """The blocks `(a, b)` of `C W Dᵀ` (`D` = `other`, the same joints) that
        `structure` (`tree_structure`, joints named by their body) says are nonzero:
        `Σ_j C_{a,j} W_j D_{b,j}ᵀ` over the bodies `j` both joints touch."""
        _, order, neighbours = structure
        index = {i: k for k, i in enumerate(self.child)}
        left = self.times_blocks(W)
        blocks = {}
        for a in order:
            left_columns = dict(left._columns(index[a]))
            for b in [a, *neighbours[a]]:
                terms = [
                    matmul(left_columns[j], rows.T)
                    for j, rows in other._columns(index[b])
                    if j in left_columns
                ]
                blocks[a, b] = sum(terms)
        return blocks

    def dense(self):
        """The `(c, N, 6)` array, assembled by static stacks (a batched scatter is a serial
        loop on CPU)."""
        rows = []
        for k in range(len(self.child)):
            columns = dict(self._columns(k))
            zero = jnp.zeros_like(self.of_child[k])
            rows.append(jnp.stack([columns.get(j, zero) for j in range(self.n_bodies)], axis=1))
        return jnp.concatenate(rows)
