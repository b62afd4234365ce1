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

from ._group_base import MatrixLieGroup

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

    def check_state(self, g0, m0) -> None:
        """Raise `ValueError` for shapes or values that cannot start a simulation."""
        from ._checks import check_finite, check_shape, is_concrete

        n, d = self.group.matrix_dim, self.group.algebra_dim
        check_shape("g0", g0, (n, n), f"a {n}×{n} group element")
        check_shape("m0", m0, (d,), f"momentum coordinates of dimension {d}")
        check_finite("g0", g0)
        check_finite("m0", m0)
        if is_concrete(g0):
            defect = float(self.group.membership_defect(jnp.asarray(g0, float)))
            if defect > 1e-6:
                raise ValueError(
                    f"`g0` is not in the group: membership defect {defect:.3g} > 1e-6 (for "
                    "SO(n): ‖g0ᵀg0 − I‖ + |det g0 − 1|). Pass a rotation matrix, e.g. "
                    "orthonormalise with a QR or polar decomposition."
                )
