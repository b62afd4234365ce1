"""The generalized rigid body on SO(n) (paper §4.2 and §5; Moser–Veselov).

The inertia operator is `J(ξ) = Λξ + ξΛ` with `Λ = diag(Λ₁, …, Λₙ)`, `Λᵢ + Λⱼ > 0`, and the
Lagrangian (5.1) is `l(ξ) = ¼ tr(ξᵀ J(ξ)) = ½ tr(ξᵀ Λ ξ)`. In the coordinates of
`lievi.SOn` this is diagonal: the coordinate of the plane `(i, j)` has inertia
`Λᵢ + Λⱼ`, and the momentum `m = ∇l(ξ)` satisfies `hat(m) = J(hat(ξ))`. For n = 3 this is
`RigidBody` with `I₁ = Λ₂ + Λ₃`, `I₂ = Λ₁ + Λ₃`, `I₃ = Λ₁ + Λ₂`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._groups._son import SOn, planes
from ._base import AbstractLieSystem
from ._potential import AbstractPotential, as_potential
from ._side import Side


class GeneralizedRigidBody(AbstractLieSystem):
    """The generalized rigid body on SO(n), n ≥ 2.

    **Arguments:**

    - `Lambda`: the diagonal of `Λ`, shape `(n,)`, with `Λᵢ + Λⱼ > 0` for all `i ≠ j`.
    - `potential`: `None`, a `lievi.AbstractPotential` or a callable `V(g)` (see
      `lievi.RigidBody`).
    """

    Lambda: Float[Array, " n"]
    potential: AbstractPotential | None
    group: SOn = eqx.field(static=True)
    side: Side = eqx.field(default=Side.LEFT, static=True)

    def __init__(self, Lambda, potential=None):
        self.potential = as_potential(potential)
        shape = jnp.shape(Lambda)
        if len(shape) != 1 or shape[0] < 2:
            raise ValueError(f"`Lambda` must be a vector of shape (n,), n ≥ 2, got shape {shape}.")
        self.Lambda = Lambda
        self.group = SOn(shape[0])

    def parameter_conditions(self):
        """Finite `Λ` with `Λᵢ + Λⱼ > 0` for all `i ≠ j`."""
        return super().parameter_conditions() + [
            (
                jnp.all(self.plane_inertia > 0),
                "`Lambda` must satisfy Λᵢ + Λⱼ > 0 for all i ≠ j (positive-definite inertia "
                "operator).",
            )
        ]

    @property
    def plane_inertia(self) -> Float[Array, " d"]:
        """`Λᵢ + Λⱼ` for each plane `(i, j)`, in the coordinate order of `SOn`."""
        i, j, _ = planes(self.group.n)
        Lambda = jnp.asarray(self.Lambda)
        return Lambda[i] + Lambda[j]

    def lambda_matrix(self) -> Float[Array, "n n"]:
        """`diag(Λ)`."""
        return jnp.diag(jnp.asarray(self.Lambda))

    def principal_planes(self):
        """`(Λᵢ + Λⱼ per plane, None)`: `Λ` is diagonal, the coordinates principal."""
        return self.plane_inertia, None

    def lagrangian(self, xi: Float[Array, " d"]) -> Scalar:
        return jnp.dot(xi, self.plane_inertia * xi) / 2

    def legendre(self, xi: Float[Array, " d"]) -> Float[Array, " d"]:
        return self.plane_inertia * xi

    def velocity(self, m: Float[Array, " d"]) -> Float[Array, " d"]:
        return m / self.plane_inertia

    def energy(self, m: Float[Array, " d"]) -> Scalar:
        return jnp.dot(m, self.velocity(m)) / 2
