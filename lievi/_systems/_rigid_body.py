"""The rigid body on SO(3) (left-invariant; paper §4.2 with n = 3, §7 with a potential).

`l(Ω) = ½ Ωᵀ I Ω`, body momentum `Π = I Ω`, kinetic energy `H(Π) = ½ Πᵀ I⁻¹ Π`. The
Euler–Poincaré equations are Euler's equations `Π̇ = Π × Ω + M(g)` with reconstruction
`ġ = g Ω̂`, where `M` is the body torque of the potential (zero for the free body).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._checks import check_real_dtype, is_concrete, spd_conditions
from .._groups._base import MatrixLieGroup
from .._groups._so3 import SO3
from ._base import AbstractLieSystem
from ._potential import AbstractPotential, UniformGravity, as_potential
from ._side import Side


class RigidBody(AbstractLieSystem):
    """A rigid body, free or in a potential.

    **Arguments:**

    - `inertia`: principal moments of inertia, shape `(3,)`, or a full symmetric positive
      definite inertia tensor, shape `(3, 3)`, in the body frame (about the fixed point
      when there is one, e.g. for a heavy top). A pytree leaf, so `jax.grad` and
      `jax.vmap` reach it.
    - `potential`: `None` (the free body), a `lievi.AbstractPotential` such as
      `lievi.UniformGravity`, or any callable `V(g)` of the attitude returning a scalar;
      the torque is derived from it by autodiff.
    """

    inertia: Float[Array, 3] | Float[Array, "3 3"]
    potential: AbstractPotential | None
    group: MatrixLieGroup = eqx.field(static=True)
    side: Side = eqx.field(static=True)

    def __init__(self, inertia, potential=None):
        self.inertia = inertia
        self.potential = as_potential(potential)
        self.group = SO3
        self.side = Side.LEFT

    def __check_init__(self):
        shape = jnp.shape(self.inertia)
        if shape not in ((3,), (3, 3)):
            raise ValueError(
                f"`inertia` must be principal moments of shape (3,) or a tensor of shape "
                f"(3, 3), got shape {shape}."
            )
        check_real_dtype("inertia", self.inertia)

    def parameter_conditions(self):
        """Finite, symmetric and positive definite inertia (`spd_conditions`)."""
        return super().parameter_conditions() + spd_conditions("inertia", self.inertia_tensor)

    @property
    def inertia_tensor(self) -> Float[Array, "3 3"]:
        inertia = jnp.asarray(self.inertia)
        return jnp.diag(inertia) if inertia.ndim == 1 else inertia

    def lambda_matrix(self) -> Float[Array, "3 3"]:
        """`Λ = ½ tr(I)·1 − I` (principal moments: `Λᵢ = ½(I₁ + I₂ + I₃) − Iᵢ`, so that
        `Λⱼ + Λₖ = Iᵢ`): `J(ξ̂) = Λξ̂ + ξ̂Λ` is `hat(I ξ)` for any symmetric `I`."""
        inertia = self.inertia_tensor
        return jnp.trace(inertia) / 2 * jnp.eye(3, dtype=inertia.dtype) - inertia

    def principal_planes(self):
        """The principal moments and the rotation into their frame: `(I, None)` for
        principal moments, the eigendecomposition of a full tensor (a proper rotation)."""
        inertia = jnp.asarray(self.inertia)
        if inertia.ndim == 1:
            return inertia, None
        moments, Q = jnp.linalg.eigh(inertia)
        # A proper rotation: flip the last axis if eigh returned a reflection.
        return moments, Q.at[:, -1].multiply(jnp.sign(jnp.linalg.det(Q)))

    def principal_body(self):
        """`RigidBody` of the principal moments (`principal_planes`), free."""
        return RigidBody(self.principal_planes()[0])

    def kinetic_tensor(self) -> Float[Array, 3] | Float[Array, "3 3"]:
        # Principal moments `(3,)` or the full tensor, as given.
        return self.inertia

    def lagrangian(self, xi: Float[Array, 3]) -> Scalar:
        return jnp.dot(xi, self.legendre(xi)) / 2

    def legendre(self, xi: Float[Array, 3]) -> Float[Array, 3]:
        inertia = jnp.asarray(self.inertia)
        return inertia * xi if inertia.ndim == 1 else inertia @ xi

    def velocity(self, m: Float[Array, 3]) -> Float[Array, 3]:
        inertia = jnp.asarray(self.inertia)
        return m / inertia if inertia.ndim == 1 else jnp.linalg.solve(inertia, m)

    def energy(self, m: Float[Array, 3]) -> Scalar:
        return jnp.dot(m, self.velocity(m)) / 2


def heavy_top(
    inertia, mass, center_of_mass, gravity=9.81, *, inertia_about: str = "fixed_point"
) -> RigidBody:
    """A heavy top: a rigid body with a fixed point in uniform gravity (paper §7).

    `RigidBody(inertia, potential=UniformGravity(mass, center_of_mass, gravity))`, with
    `center_of_mass` `ρ` measured from the fixed point in the body frame. A Lagrange top
    has `I₁ = I₂` and the centre of mass on the third axis; a long arm (`|ρ|` large against
    the radius of gyration) makes it a 3-D pendulum.

    `inertia_about`: `"fixed_point"` (the default: `inertia` is about the fixed point, the
    tensor the equations use) or `"center_of_mass"` (as MuJoCo and most CAD tools give it:
    the parallel-axis theorem moves it to the fixed point, `I_O = I_C + m(|ρ|²1 − ρρᵀ)`; the
    result is a full tensor unless `ρ` lies on a principal axis, and principal moments
    stay principal moments then).
    """
    if inertia_about not in ("fixed_point", "center_of_mass"):
        raise ValueError(
            f"`inertia_about` must be 'fixed_point' or 'center_of_mass', got {inertia_about!r}."
        )
    if inertia_about == "center_of_mass":
        inertia = _parallel_axis(inertia, mass, center_of_mass)
    return RigidBody(inertia, potential=UniformGravity(mass, center_of_mass, gravity))


def _parallel_axis(inertia, mass, rho):
    """`I_C + m(|ρ|²1 − ρρᵀ)`: moments `(3,)` stay moments where `ρ` is (concretely) on a
    principal axis (the shift is then diagonal), else a `(3, 3)` tensor."""
    inertia, rho = jnp.asarray(inertia), jnp.asarray(rho)
    # The identity in the inputs' dtype: a default (float64 under x64) `eye` made a float32
    # top's inertia, and so its whole run, float64.
    eye = jnp.eye(3, dtype=jnp.result_type(inertia, rho))
    shift = mass * (jnp.dot(rho, rho) * eye - jnp.outer(rho, rho))
    if jnp.ndim(inertia) == 1:
        on_axis = is_concrete(rho) and int(np.count_nonzero(np.asarray(rho))) <= 1
        if on_axis:
            return inertia + jnp.diagonal(shift)
        inertia = jnp.diag(inertia)
    return inertia + shift
