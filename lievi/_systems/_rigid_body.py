"""The free rigid body on SO(3) (left-invariant; paper §4.2 with n = 3).

`l(Ω) = ½ Ωᵀ I Ω`, body momentum `Π = I Ω`, energy `H(Π) = ½ Πᵀ I⁻¹ Π`. The Euler–Poincaré
equations are Euler's equations `Π̇ = Π × Ω` with reconstruction `ġ = g Ω̂`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._batch import _fast_so3
from .._checks import check_spd
from .._groups._base import MatrixLieGroup
from .._groups._so3 import SO3
from ._base import AbstractLieSystem


class RigidBody(AbstractLieSystem):
    """A free rigid body.

    **Arguments:**

    - `inertia`: principal moments of inertia, shape `(3,)`, or a full symmetric positive
      definite inertia tensor, shape `(3, 3)`, in the body frame. A pytree leaf, so
      `jax.grad` and `jax.vmap` reach it.
    """

    inertia: Float[Array, "3"] | Float[Array, "3 3"]
    group: MatrixLieGroup = eqx.field(static=True)
    side: str = eqx.field(static=True)

    def __init__(self, inertia):
        self.inertia = inertia
        self.group = SO3
        self.side = "left"

    def __check_init__(self):
        shape = jnp.shape(self.inertia)
        if shape not in ((3,), (3, 3)):
            raise ValueError(
                f"`inertia` must be principal moments of shape (3,) or a tensor of shape "
                f"(3, 3), got shape {shape}."
            )
        check_spd("inertia", self.inertia_tensor)

    @property
    def inertia_tensor(self) -> Float[Array, "3 3"]:
        inertia = jnp.asarray(self.inertia)
        return jnp.diag(inertia) if inertia.ndim == 1 else inertia

    def principal_moments(self, batched: bool = False):
        inertia = jnp.asarray(self.inertia)
        return inertia if inertia.ndim == 1 + batched else None

    def kernel_step(self, kernel, g, m, h):
        # The structure-of-arrays step on one body: every component a scalar (under
        # `jax.vmap` a `(B,)` array, so `vmap(simulate)` runs the batched kernel).
        moments = self.principal_moments()
        if kernel is None or moments is None:
            return None
        params = kernel.prepare(tuple(moments[i] for i in range(3)), h)
        components = tuple(g[i, j] for i in range(3) for j in range(3))
        g_next, m_next, *info = kernel.step(params, components, tuple(m[i] for i in range(3)), True)
        return (jnp.stack(g_next).reshape(3, 3), jnp.stack(m_next), *info)

    def closed_form_residual(self, equation: str, m, h):
        # Closed forms for principal moments (`lievi._batch._fast_so3`, where they are
        # derived and checked against `jax.jacfwd`); a full tensor uses the generic path.
        inertia = jnp.asarray(self.inertia)
        if inertia.ndim != 1:
            return None
        A = tuple(inertia[i] / h for i in range(3))
        Pi = tuple(m[i] for i in range(3))

        def residual_and_jacobian(x):
            r, J = _fast_so3._residual(equation, tuple(x[i] for i in range(3)), Pi, A, True)
            return jnp.stack(r), jnp.stack([jnp.stack(row) for row in J])

        return residual_and_jacobian

    def lagrangian(self, xi: Float[Array, "3"]) -> Scalar:
        return jnp.dot(xi, self.legendre(xi)) / 2

    def legendre(self, xi: Float[Array, "3"]) -> Float[Array, "3"]:
        inertia = jnp.asarray(self.inertia)
        return inertia * xi if inertia.ndim == 1 else inertia @ xi

    def velocity(self, m: Float[Array, "3"]) -> Float[Array, "3"]:
        inertia = jnp.asarray(self.inertia)
        return m / inertia if inertia.ndim == 1 else jnp.linalg.solve(inertia, m)

    def energy(self, m: Float[Array, "3"]) -> Scalar:
        return jnp.dot(m, self.velocity(m)) / 2
