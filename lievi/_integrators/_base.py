"""The integrator interface: a one-step map on `(g, m)` that reports a result code.

An integrator is an `eqx.Module` (its settings are fields). `step` advances the group
element and the momentum by one step `h` and returns a `StepInfo`. Variational
integrators also expose their discrete Lagrangian `L_d(g_k, g_{k+1})`, from which the
diagnostics check the discrete Euler–Lagrange equations (2.1) by autodiff.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, Scalar

from .._results import RESULTS
from .._batch._kernel import KickKernel
from .._systems._base import AbstractLieSystem


class StepInfo(eqx.Module):
    """Per-step report: `result` code, Newton `iterations`, final `residual` (∞-norm)."""

    result: Int[Array, ""]
    iterations: Int[Array, ""]
    residual: Float[Array, ""]


class AbstractIntegrator(eqx.Module):
    """A one-step method for a `AbstractLieSystem`."""

    @abc.abstractmethod
    def order(self) -> int:
        """Classical order of accuracy."""

    def is_symmetric(self) -> bool:
        """Whether `Φ_{−h} = Φ_h⁻¹` (time-reversible); `Composition` needs it."""
        return False

    @abc.abstractmethod
    def step(
        self, system: AbstractLieSystem, g: Float[Array, "n n"], m: Float[Array, " d"], h: Scalar
    ) -> tuple[Float[Array, "n n"], Float[Array, " d"], StepInfo]:
        """Advance `(g_k, m_k)` to `(g_{k+1}, m_{k+1})`."""

    def batch_kernel(self, potential=None):
        """This method's structure-of-arrays step for batches of rigid bodies with principal
        moments in `potential` (`None`: free bodies), an `AbstractBatchKernel`, or `None`
        where it has none.

        `simulate_batch` runs it when the system has principal moments
        (`AbstractLieSystem.principal_moments`); it computes the iterates of `step`.
        """
        return None


class AbstractKickIntegrator(AbstractIntegrator):
    """An integrator whose step, for a system with a potential, is kick – free step – kick.

    The step is `m⁺ = m_k + (h/2) M(g_k)`, `(g_{k+1}, m⁻) = free_step(g_k, m⁺)`,
    `m_{k+1} = m⁻ + (h/2) M(g_{k+1})` with `M` the system's generalised force
    (`AbstractLieSystem.kick`). For a variational method with discrete Lagrangian
    `L_d − (h/2)(V(g_k) + V(g_{k+1}))` this *is* its discrete Euler–Lagrange equation in
    momentum form (the discrete Legendre transforms `∓D_{1,2}L_d` pick up `∓(h/2)dV`); for
    a splitting it is the symmetric Strang composition with the exact flow of `V`. Either
    way symmetric and second order when the free step is, and nothing changes for a free
    system (the kicks are skipped at trace time).
    """

    @abc.abstractmethod
    def free_step(
        self, system: AbstractLieSystem, g: Float[Array, "n n"], m: Float[Array, " d"], h: Scalar
    ) -> tuple[Float[Array, "n n"], Float[Array, " d"], StepInfo]:
        """The step of the system without its potential."""

    def free_batch_kernel(self):
        """The structure-of-arrays `free_step` for batches of rigid bodies, or `None`."""
        return None

    def batch_kernel(self, potential=None):
        free = self.free_batch_kernel()
        if free is None or potential is None:
            return free
        if not KickKernel.applies_to(potential):
            return None
        # Kick – free step – kick, as `step`, where the potential has a closed-form torque.
        return KickKernel(free, potential)

    def step(self, system: AbstractLieSystem, g, m, h: Scalar):
        if system.potential is None:
            return self.free_step(system, g, m, h)
        g_next, m_next, info = self.free_step(system, g, system.kick(g, m, h / 2), h)
        m_next = system.kick(g_next, m_next, h / 2)
        # A non-finite potential or force shows up only after the free step's own checks.
        nonfinite = (info.result == RESULTS.successful) & ~jnp.all(jnp.isfinite(m_next))
        result = jnp.where(nonfinite, RESULTS.nonfinite, info.result)
        return g_next, m_next, StepInfo(result, info.iterations, info.residual)


class AbstractVariationalIntegrator(AbstractKickIntegrator):
    """An integrator defined by a discrete Lagrangian `L_d(g_k, g_{k+1})` (paper §2)."""

    @abc.abstractmethod
    def kinetic_discrete_lagrangian(
        self, system: AbstractLieSystem, g0: Float[Array, "n n"], g1: Float[Array, "n n"], h: Scalar
    ) -> Scalar:
        """`L_d` of the reduced Lagrangian `l(ξ)` alone (the free system)."""

    def discrete_lagrangian(
        self, system: AbstractLieSystem, g0: Float[Array, "n n"], g1: Float[Array, "n n"], h: Scalar
    ) -> Scalar:
        """`L_d(g_k, g_{k+1})`: the kinetic part minus `(h/2)(V(g_k) + V(g_{k+1}))`.

        The trapezoidal potential term makes the step kick – free step – kick (see
        `AbstractKickIntegrator`); it is the Lie group variational integrator of Lee, Leok
        and McClamroch for the exponential/Cayley charts.
        """
        kinetic = self.kinetic_discrete_lagrangian(system, g0, g1, h)
        if system.potential is None:
            return kinetic
        return kinetic - h / 2 * (system.potential_energy(g0) + system.potential_energy(g1))

    def momentum_from_configurations(
        self, system: AbstractLieSystem, g0: Float[Array, "n n"], g1: Float[Array, "n n"], h: Scalar
    ) -> Float[Array, " d"]:
        """The momentum at `g0` of the discrete trajectory through `(g0, g1)`.

        The discrete Legendre transform `m_0 = −D₁L_d(g_0, g_1)`, trivialised on the
        side of the symmetry (paper §2); computed by autodiff of `discrete_lagrangian`.
        """
        group = system.group

        def perturbed(eta):
            e = group.exp(eta)
            g = g0 @ e if system.side == "left" else e @ g0
            return self.discrete_lagrangian(system, g, g1, h)

        return -jax.grad(perturbed)(jnp.zeros(group.algebra_dim, g0.dtype))
