"""Lagrangian systems on a Lie group, reduced to the algebra (paper §2, §4.2).

A system is a reduced Lagrangian `l: g → R` on algebra coordinates together with the
group and the side of the symmetry: `side="left"` for left-invariant systems such as
the rigid body (`ξ = g⁻¹ġ`, body momentum `Π`), `side="right"` for right-invariant ones
(`ξ = ġ g⁻¹`, spatial momentum `μ`). The momentum is `m = ∂l/∂ξ` (the Legendre map),
written in the coordinates dual to the algebra basis.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._checks import check_finite, check_shape, is_concrete
from .._groups._base import MatrixLieGroup

SIDES = ("left", "right")


class AbstractLieSystem(eqx.Module):
    """A reduced Lagrangian system on a matrix Lie group.

    Subclasses set `group` and `side` and implement `lagrangian`. The Legendre map, its
    inverse and the energy have generic versions (autodiff and Newton) that quadratic
    systems override with closed forms.
    """

    group: eqx.AbstractVar[MatrixLieGroup]
    side: eqx.AbstractVar[str]

    @abc.abstractmethod
    def lagrangian(self, xi: Float[Array, " d"]) -> Scalar:
        """The reduced Lagrangian `l(ξ)`."""

    def legendre(self, xi: Float[Array, " d"]) -> Float[Array, " d"]:
        """Momentum `m = ∇l(ξ)`."""
        return jax.grad(self.lagrangian)(xi)

    def velocity(self, m: Float[Array, " d"], iterations: int = 30) -> Float[Array, " d"]:
        """Inverse Legendre map: `ξ` with `∇l(ξ) = m` (Newton from `ξ = 0`)."""

        def body(_, xi):
            hessian = jax.hessian(self.lagrangian)(xi)
            return xi - jnp.linalg.solve(hessian, self.legendre(xi) - m)

        return jax.lax.fori_loop(0, iterations, body, jnp.zeros_like(m))

    def energy(self, m: Float[Array, " d"]) -> Scalar:
        """Hamiltonian `H(m) = ⟨m, ξ⟩ − l(ξ)` with `ξ` the velocity of `m`."""
        xi = self.velocity(m)
        return jnp.dot(m, xi) - self.lagrangian(xi)

    def principal_moments(self, batched: bool = False):
        """Principal moments of inertia `(3,)` (`(B, 3)` for a batch of systems built with
        `jax.vmap`, `batched=True`) if this is a rigid body on SO(3) whose fast batched
        steps apply (`AbstractIntegrator.batch_kernel`), else `None`."""
        return None

    def closed_form_residual(self, equation: str, m, h):
        """`x ↦ (r(x), ∂r/∂x)` for the implicit step equation `equation` (`"exp"`, `"cayley"`:
        `DEP`'s chart; `"moser-veselov"`), written out by hand, or `None` (the integrator
        then builds `r` from the group and the Lagrangian and its Jacobian by `jax.jacfwd`)."""
        return None

    def kernel_step(self, kernel, g, m, h):
        """One step of `kernel` (an integrator's `batch_kernel`) on this one system, as
        `(g_next, m_next, result, iterations, residual)`, or `None` where the kernel does not
        apply (the integrator then takes its generic step)."""
        return None

    def check_element(self, name: str, g) -> None:
        """Raise `ValueError` unless `g` is an `(n, n)` finite element of the group."""
        n = self.group.matrix_dim
        check_shape(name, g, (n, n), f"a {n}×{n} group element")
        check_finite(name, g)
        if is_concrete(g):
            # Evaluated now even when `simulate` is being traced by an outer `jit` with a
            # concrete `g` captured from outside.
            with jax.ensure_compile_time_eval():
                defect = float(self.group.membership_defect(jnp.asarray(g, float)))
            if defect > 1e-6:
                raise ValueError(
                    f"`{name}` is not in the group: membership defect {defect:.3g} > 1e-6 "
                    "(for SO(n): ‖gᵀg − I‖ + |det g − 1|). Pass a rotation matrix, e.g. "
                    "orthonormalise with a QR or polar decomposition."
                )

    def check_momentum(self, name: str, m) -> None:
        """Raise `ValueError` unless `m` is a finite `(d,)` momentum."""
        d = self.group.algebra_dim
        check_shape(name, m, (d,), f"momentum coordinates of dimension {d}")
        check_finite(name, m)
