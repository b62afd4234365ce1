"""The kick – free step – kick kernel: a free kernel between two half kicks of a potential.

The structure-of-arrays form of `AbstractKickIntegrator`'s step (paper §7), for
potentials linear in `g`, `V = aᵀ g b` (`AbstractPotential.linear_coupling`), whose
rigid-body torque is `M = Γ × b` with `Γ = gᵀa`.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._groups._so3 import SO3
from .._results import RESULTS
from ._base import AbstractBatchKernel
from ._scheme import SplittingScheme


def rigid_body_coupling(potential) -> bool:
    """Whether `potential` is linear in a rigid body's attitude, `V = aᵀ g b` with `a`, `b`
    3-vectors (`AbstractPotential.linear_coupling`): its torque is then `Γ × b`."""
    coupling = potential.linear_coupling()
    return coupling is not None and all(jnp.shape(v)[-1:] == (3,) for v in coupling)


def advected_rows(a, g):
    """`Γ = gᵀa` from the 9 entries of `g` (row-major); `a` may carry a batch axis first."""
    a = jnp.asarray(a, g[0].dtype)
    return tuple(sum(a[..., i] * g[3 * i + j] for i in range(3)) for j in range(3))


def coupling_torque(b, Gamma):
    """`Γ × b`, the body torque of `V = aᵀ g b` (`Γ = gᵀa`), as 3 arrays."""
    b = tuple(b[..., i] for i in range(3))
    return (
        Gamma[1] * b[2] - Gamma[2] * b[1],
        Gamma[2] * b[0] - Gamma[0] * b[2],
        Gamma[0] * b[1] - Gamma[1] * b[0],
    )


class KickKernel(AbstractBatchKernel):
    """A free kernel between two half kicks of a potential's torque (paper §7): the step of
    `AbstractKickIntegrator` (`Π⁺ = Π + (h/2)M(g_k)`, free step, `Π_{k+1} = Π⁻ + (h/2)M(g_{k+1})`)
    for a potential linear in `g`, `V = aᵀ g b` (`AbstractPotential.linear_coupling`, e.g.
    `UniformGravity`): the torque is `M = Γ × b` with `Γ = gᵀa`.

    With `reduced_state` (see `reduced`) the configuration carried is the advected
    parameter `Γ = gᵀa` alone, and the kicks are `M(Γ)`: the free kernel maps `Γᵀ`, one
    row, as it maps each row of `g` (`r ↦ r F_k`), so `Γ_{k+1} = F_kᵀΓ_k` — the
    Bobenko–Suris reduced discrete Lie–Poisson equations on `(Π, Γ)` (paper §7), with
    the same floating-point operations on `Π` and on `Γ` as the run that carries `g`.
    """

    free: AbstractBatchKernel
    potential: eqx.Module
    reduced_state: bool = eqx.field(default=False, static=True)

    @staticmethod
    def applies_to(potential) -> bool:
        """Whether `potential` is linear in a rigid body's attitude (`linear_coupling`)."""
        return rigid_body_coupling(potential)

    def physics(self, system, batched: bool = False):
        # The torques are those of a rigid body on SO(3).
        if system.group != SO3 or not self.applies_to(self.potential):
            return None
        return self.free.physics(system, batched)

    def constants(self, values):
        return self.free.constants(values)

    def turn_rates(self, constants, h):
        return self.free.turn_rates(constants, h)

    def turn_squared(self, rates, m):
        return self.free.turn_squared(rates, m)

    def with_fixed_iterations(self, fixed_iterations: int):
        return dataclasses.replace(self, free=self.free.with_fixed_iterations(fixed_iterations))

    def one_body(self):
        # The free kernel as it runs one body, as `simulate` and `Tuning(fast=False)`
        # promise: kept as is, the kicks would run the batch's form there.
        return dataclasses.replace(self, free=self.free.one_body())

    def reduced(self):
        # `V = aᵀ g b` depends on `g` through `Γ = gᵀa` alone.
        return self if self.reduced_state else dataclasses.replace(self, reduced_state=True)

    def _advected_of_rows(self, g):
        return advected_rows(self.potential.linear_coupling()[0], g)

    def carried(self, g0):
        g = super().carried(g0)
        return self._advected_of_rows(g) if self.reduced_state else g

    def advected(self, state):
        return state if self.reduced_state else self._advected_of_rows(state)

    def _torque(self, state):
        """`M = Γ × b` from the carried state (`Γ` itself, or the 9 entries of `g`)."""
        Gamma = state if self.reduced_state else self._advected_of_rows(state)
        return coupling_torque(self.potential.linear_coupling()[1], Gamma)

    def prepare(self, inertia, h):
        return self.free.prepare(inertia, h), h / 2

    def step(self, params, g, m, alive):
        free_params, half = params
        m = self._kicked(m, half, g)
        g_next, m_next, result, iterations, residual = self.free.step(free_params, g, m, alive)
        m_next = self._kicked(m_next, half, g_next)
        return g_next, m_next, _nonfinite(result, m_next), iterations, residual

    def _kicked(self, m, weight, state):
        """`Π + weight·M(state)`."""
        return tuple(p + weight * t for p, t in zip(m, self._torque(state)))

    def prepare_stages(self, inertia, h, coefficients: tuple[float, ...]):
        # The composition of kick – free step – kick at the stages `γ_i h`: the splitting
        # scheme `a_i = γ_i` with the merged kicks `(γ_i + γ_{i+1})/2` (`_scheme.py`).
        return self.prepare_scheme(inertia, h, SplittingScheme.from_composition(coefficients))

    def prepare_scheme(self, inertia, h, scheme: SplittingScheme):
        """Per-run constants of `step_stages` for a splitting scheme `(a, b)`: the free
        steps `a_i h`, stacked; the first kick `b_0 h`; after stage `i` the kick `b_i h`."""
        free = [self.free.prepare(inertia, a * h) for a in scheme.drifts]
        after = [b * h for b in scheme.kicks[1:]]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *free), scheme.kicks[0] * h, jnp.stack(after)

    def step_stages(self, params, g, m, alive):
        """The splitting scheme of `prepare_scheme` (kick `b_0 h`, then free step `a_i h`
        and kick `b_i h` per stage). For the composition `Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}` of
        kick – free step – kick (`prepare_stages`) the half kicks of adjacent stages are
        merged: stage `i` ends and stage `i + 1` begins at the same `g_i`, so
        `Π + (γ_i h/2)M(g_i) + (γ_{i+1} h/2)M(g_i)` is one kick
        `Π + ((γ_i + γ_{i+1}) h/2)M(g_i)` — `s + 1` torques a step, not `2s`, and the same
        map (equal to the unmerged stages to round-off: one addition fewer per merge). A
        non-finite torque is caught once, at the end of the step (it propagates through
        the stages)."""
        free, first, after = params
        m = self._kicked(m, first, g)

        def stage(carry, stage_params):
            g, m, result, iterations, residual = carry
            free_params, weight = stage_params
            g, m, code, its, res = self.free.step(free_params, g, m, alive)
            m = self._kicked(m, weight, g)
            result = RESULTS.first_failure(result, code)
            return (g, m, result, iterations + its, jnp.maximum(residual, res)), None

        zeros = jnp.zeros(jnp.shape(m[0]), jnp.int32)
        init = (g, m, zeros + RESULTS.successful, zeros, jnp.zeros_like(m[0]))
        carry, _ = jax.lax.scan(stage, init, (free, after))
        g, m, result, iterations, residual = carry
        return g, m, _nonfinite(result, m), iterations, residual


def _nonfinite(result, m):
    """`result`, or `nonfinite` where it is a success but `m` is not finite: a non-finite
    torque shows up only after the free step's own checks."""
    finite = jnp.isfinite(m[0]) & jnp.isfinite(m[1]) & jnp.isfinite(m[2])
    return jnp.where((result == RESULTS.successful) & ~finite, RESULTS.nonfinite, result)
