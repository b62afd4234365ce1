"""The fused batched step of a `Composition`: the inner method's kernel at each stage.

`Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}` as one structure-of-arrays step: the per-run constants of every
stage (`γ_i h`) are prepared once, and the stages run as a loop over them on the same
structure-of-arrays state inside the one loop of `simulate_batch` — instead of
`jax.vmap(simulate)` of the per-body composition. The iterates are the per-body
composition's (the kernel parity test).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._results import RESULTS
from ._base import AbstractBatchKernel


class CompositionKernel(AbstractBatchKernel):
    """`inner`'s kernel at the stages `γ_i h` of a symmetric composition (`coefficients`)."""

    inner: AbstractBatchKernel
    coefficients: tuple[float, ...] = eqx.field(static=True)

    def _wrap(self, inner):
        return None if inner is None else dataclasses.replace(self, inner=inner)

    def physics(self, system, batched: bool = False):
        return self.inner.physics(system, batched)

    def constants(self, values):
        return self.inner.constants(values)

    def prepare(self, constants, h):
        # Each stage's constants for its own step `γ_i h`, once per run, stacked along a
        # leading axis of stages: the stages are a loop over them (`step`).
        stages = [self.inner.prepare(constants, gamma * h) for gamma in self.coefficients]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *stages)

    def step(self, params, g, m, alive):
        # A loop over the stages, not the stages written out: one stage's code is compiled.
        # Written out, the 9- and 17-stage compositions compiled 4–17× the inner step's
        # code, and on a GPU ran at a half to a quarter of the rate their stage count predicts.
        return self.stages(params, g, m, alive)

    def stages(self, params, g, m, alive, unroll: int | bool = 1):
        """The stages in one `lax.scan` (`unroll` is the scan's; `step` keeps the loop, and
        the retired `composition_unroll_experiment.py` timed it against `unroll=True`)."""

        def stage(carry, stage_params):
            g, m, result, iterations, residual = carry
            g, m, code, its, res = self.inner.step(stage_params, g, m, alive)
            result = RESULTS.first_failure(result, code)
            return (g, m, result, iterations + its, jnp.maximum(residual, res)), None

        zeros = jnp.zeros(jnp.shape(m[0]), jnp.int32)
        init = (g, m, zeros + RESULTS.successful, zeros, jnp.zeros_like(m[0]))
        (g, m, result, iterations, residual), _ = jax.lax.scan(stage, init, params, unroll=unroll)
        return g, m, result, iterations, residual

    # The step bound is the integrator's (`Composition.step_bound`), on the full step.
    def turn_rates(self, constants, h):
        return self.inner.turn_rates(constants, h)

    def turn_squared(self, rates, m):
        return self.inner.turn_squared(rates, m)

    def with_fixed_iterations(self, fixed_iterations: int):
        return self._wrap(self.inner.with_fixed_iterations(fixed_iterations))

    def one_body(self):
        return self._wrap(self.inner.one_body())

    def reduced(self):
        return self._wrap(self.inner.reduced())

    def carried(self, g0):
        return self.inner.carried(g0)

    def elements(self, entries):
        return self.inner.elements(entries)

    def advected(self, state):
        return self.inner.advected(state)
