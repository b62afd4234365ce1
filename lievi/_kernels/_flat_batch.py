"""Under `jax.vmap`, a kernel's Newton solve runs on the batch as more bodies.

A kernel's solve is written for a batch of bodies (`(B,)` arrays, or scalars for one
body): fixed iterations, then a loop for the stragglers, its control a reduction over the
bodies ("any body still above tolerance"), the stragglers gathered into a small batch
(`_base.compacted_tail`) or, for one body, behind a `lax.cond`. Batched by `jax.vmap` — a
batch of `lievi.RigidBodies` systems, each running its `N` bodies through `bodies_step`;
`jax.vmap(simulate)` of one body — the loop's predicate is batched: every iteration then
runs on the whole batch under a select, and the `cond` runs both branches, so the
straggler loop costs a pass over every body at every step that any body needs it
(`jax.vmap(simulate)` of SE(3) bodies at coarse steps ran at a quarter of
`simulate_batch`). `bodies_batched(fn)` gives the solve
a batching rule of its own: the vmapped axis is merged into the body axis and `fn` runs
once on the `B·N` bodies, as in `simulate_batch`, then the axis is split again.

It is exact because such a solve computes each body's values elementwise: which bodies
share its arrays only decides how many iterations the loop runs, and a body that has
converged is left alone. The solve is never differentiated (it runs on
`stop_gradient`-ed inputs; the root's derivative is `_implicit.differentiable_root`'s),
so the rule needs no derivative of its own (`jax.custom_batching.custom_vmap` has none
for reverse mode).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp


def bodies_batched(fn):
    """`fn(*args)`, whose array arguments and outputs are per body (all of one shape, the
    bodies', or scalars shared by them), batched by merging a `jax.vmap` axis into the
    body axis. Settings that are not arrays go in by closure."""
    wrapped = jax.custom_batching.custom_vmap(fn)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        leaves, tree = jax.tree.flatten(args)
        batched = jax.tree.leaves(in_batched)
        shapes = [jnp.shape(x)[1:] if b else jnp.shape(x) for x, b in zip(leaves, batched)]
        bodies = jnp.broadcast_shapes(*shapes)
        count = axis_size * math.prod(bodies)

        def merge(x, b):
            if not b and jnp.ndim(x) == 0:
                return x  # shared by every body of every system: stays a scalar
            if b:  # `(axis_size, *s)`, `s` the bodies' shape or `()`: align `s` right
                x = x.reshape(x.shape[:1] + (1,) * (len(bodies) - x.ndim + 1) + x.shape[1:])
            return jnp.broadcast_to(x, (axis_size, *bodies)).reshape(count)

        merged = [merge(x, b) for x, b in zip(leaves, batched)]
        outputs = wrapped(*jax.tree.unflatten(tree, merged))
        split = jax.tree.map(lambda y: y.reshape(axis_size, *bodies, *y.shape[1:]), outputs)
        return split, jax.tree.map(lambda _: True, outputs)

    return wrapped
