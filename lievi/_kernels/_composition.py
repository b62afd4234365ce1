"""The fused batched step of a `Composition`: the inner method's kernel at each stage.

`Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}` as one structure-of-arrays step: the per-run constants of every
stage (`γ_i h`) are prepared once, and the stages run as a loop over them on the same
structure-of-arrays state inside the one loop of `simulate_batch` — instead of
`jax.vmap(simulate)` of the per-body composition. The inner kernel runs the stages
(`AbstractBatchKernel.step_stages`), so that a kernel whose adjacent stages share work
can share it: a kick kernel's `s` stages take `s + 1` kicks, not `2s` (`_kick.py`). The
iterates are the per-body composition's to round-off (the kernel parity test).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx

from ._base import AbstractBatchKernel
from ._scheme import SplittingScheme


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
        # Each stage's constants for its own step `γ_i h`, once per run: the inner kernel
        # lays them out for its own stage loop (`step_stages`).
        return self.inner.prepare_stages(constants, h, self.coefficients)

    def step(self, params, g, m, alive):
        # The inner kernel's stage loop: by default a `lax.scan` of its step over the
        # stages; a kick kernel's merges the half kicks of adjacent stages (`_kick.py`).
        return self.inner.step_stages(params, g, m, alive)

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

    def carried_momentum(self, m0):
        return self.inner.carried_momentum(m0)

    def elements(self, entries):
        return self.inner.elements(entries)

    def advected(self, state):
        return self.inner.advected(state)


class SchemeKernel(CompositionKernel):
    """A kick kernel (`KickKernel`) at the stages of a splitting scheme `(a, b)` whose kick
    weights are its own (`_scheme.py`; `lievi.SymmetricTopSplitting`), not those of a
    composition: `coefficients` are the drift weights `a_i`."""

    scheme: SplittingScheme = eqx.field(static=True, kw_only=True)

    def prepare(self, constants, h):
        return self.inner.prepare_scheme(constants, h, self.scheme)
