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

    def batch_kernel(self):
        """This method's structure-of-arrays step for batches of rigid bodies with principal
        moments (an `AbstractBatchKernel`), or `None` where it has none.

        `simulate_batch` runs it when the system has principal moments
        (`AbstractLieSystem.principal_moments`); it computes the iterates of `step`.
        """
        return None


class AbstractVariationalIntegrator(AbstractIntegrator):
    """An integrator defined by a discrete Lagrangian `L_d(g_k, g_{k+1})` (paper §2)."""

    @abc.abstractmethod
    def discrete_lagrangian(
        self, system: AbstractLieSystem, g0: Float[Array, "n n"], g1: Float[Array, "n n"], h: Scalar
    ) -> Scalar:
        """`L_d(g_k, g_{k+1})`."""

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
