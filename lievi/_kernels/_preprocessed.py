"""The batched step of `PreprocessedMoserVeselov`: the Moser–Veselov kernel on each body's
modified moments.

The preprocessed method is one Moser–Veselov step on the body whose inverse inertia is
`α(h) I⁻¹ + β(h)·Id`, with `α`, `β` functions of the step and of the trajectory's energy and
Casimir, which the step keeps. That body is diagonal in the principal frame (moments
`1/(α/I_i + β)`), so a run is the Moser–Veselov kernel with per-body moments computed once,
from each body's `m0` and `h`, in the run's set-up (`prepare_run`): no per-body
integrator under `jax.vmap`, and the step is plain DMV's structure-of-arrays step. A batch
that shares one body fits them from a few sample trajectories instead (`shared`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from ._base import AbstractBatchKernel


class PreprocessedKernel(AbstractBatchKernel):
    """`inner` (the Moser–Veselov kernel) on the modified principal moments of each body.

    `moments(principal, m0, h, order)`: the modified principal moments `(3,)` of one body
    (principal moments `(3,)`, initial momentum `(3,)`, step `h`); `order`: the method's.
    `shared(principal, m0s, h, order)`: the same for every body of a batch sharing
    `principal`, `(B, 3)` at once, from `order/2` sample trajectories (the coefficients are
    polynomials in each body's energy and Casimir: ~9 µs per body at order 8 computed per
    body, a few flops per body fitted). The step-size check stays on the body's own moments
    (`turn_rates`), as the generic step's `step_too_large`.
    """

    inner: AbstractBatchKernel
    moments: Callable = eqx.field(static=True)
    shared: Callable = eqx.field(static=True)
    order: int = eqx.field(static=True)

    def _wrap(self, inner):
        return dataclasses.replace(self, inner=inner)

    def prepare(self, inertia, h):
        raise NotImplementedError(
            "The preprocessed Moser–Veselov kernel depends on each trajectory: `prepare_run`."
        )

    def prepare_run(self, constants, m0, h):
        # One body shared by a batch larger than the fit's samples: fitted (cheaper).
        if all(jnp.ndim(c) == 0 for c in constants) and m0.shape[0] > self.order // 2:
            modified = self.shared(jnp.stack(constants), m0, h, self.order)
            return self.inner.prepare(tuple(modified[:, i] for i in range(3)), h)
        batch = m0.shape[0]
        principal = jnp.stack(jnp.broadcast_arrays(*constants, jnp.zeros(batch, m0.dtype)))[:3]
        h_axis = None if jnp.ndim(h) == 0 else 0
        modified = jax.vmap(
            lambda principal, m, h: self.moments(principal, m, h, self.order),
            in_axes=(1, 0, h_axis),
        )(principal, m0, h)
        return self.inner.prepare(tuple(modified[:, i] for i in range(3)), h)

    def step(self, params, g, m, alive):
        return self.inner.step(params, g, m, alive)

    def with_fixed_iterations(self, fixed_iterations: int):
        return self._wrap(self.inner.with_fixed_iterations(fixed_iterations))

    def one_body(self):
        return self._wrap(self.inner.one_body())
