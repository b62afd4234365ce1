"""A rigid body moving in space: a left-invariant system on SE(3) (paper §2, §4.2).

Velocity `ξ = g⁻¹ġ = (ω, v)` (body angular velocity, body-frame velocity of the body
origin; twist order of `lievi.SE3`), kinetic energy `l(ξ) = ½ ξᵀ M ξ` with a symmetric
positive definite 6×6 tensor `M`, momentum `m = M ξ = (Π, P)`. The Euler–Poincaré
equations `ṁ = ad_ξᵀ m` are **Kirchhoff's equations**

    Π̇ = Π × ω + P × v,     Ṗ = P × ω,     ġ = g ξ̂,

the motion of a rigid body in an ideal fluid at rest (Lamb, *Hydrodynamics* (1932) §124–126;
Leonard, *Stability of a bottom-heavy underwater vehicle*, Automatica 33 (1997)), where
`M` is the body's own mass tensor plus the fluid's added mass. They are Lie–Poisson on
`se(3)*` with Casimirs `|P|²` and `P·Π` (`lievi.SE3.casimirs`). For a body in vacuum
with its origin at the centre of mass, `M = diag(J, m I)`; then `P = m v` is constant in
space and `Π` obeys Euler's equations.

A potential `V(g)` adds the body-frame wrench `M(g) = −d/dε V(g exp(ε e_i))` (torque,
force; `AbstractLieSystem.force`) to the right-hand side (paper §7): uniform gravity
(`lievi.UniformGravitySE3`), or the central gravity of a planet on a mass distribution
(`lievi.CentralGravity`, the full body problem).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._checks import check_finite, check_spd, is_concrete, spd_conditions
from .._groups._base import MatrixLieGroup
from .._groups._se3 import SE3
from ._base import AbstractLieSystem
from ._bodies import regular_inertia
from ._potential import AbstractPotential, as_potential
from ._side import Side


@jax.jit
def spd_solve(M: Float[Array, "k k"], b: Float[Array, " k"]) -> Float[Array, " k"]:
    """`M⁻¹ b` for a small SPD `M` by an unrolled Cholesky factorisation.

    Written with scalar operations so that XLA fuses it into a few instructions; a LAPACK
    call per solve (`jnp.linalg.solve`) costs more than the rest of an RK4 stage on CPU,
    especially under `vmap`. Under `jax.jit`, so that its hundred-odd operations are traced
    once per shape and dtype, not at each call (RATTLE's step calls it nine times).
    """
    k = b.shape[-1]
    M = (M + M.T) / 2  # reads both triangles: the derivative is the symmetric one
    L = [[None] * k for _ in range(k)]
    for j in range(k):
        diagonal = M[j, j] - sum(L[j][i] * L[j][i] for i in range(j))
        L[j][j] = jnp.sqrt(diagonal)
        for r in range(j + 1, k):
            L[r][j] = (M[r, j] - sum(L[r][i] * L[j][i] for i in range(j))) / L[j][j]
    y = [None] * k
    for r in range(k):  # L y = b
        y[r] = (b[r] - sum(L[r][i] * y[i] for i in range(r))) / L[r][r]
    x = [None] * k
    for r in reversed(range(k)):  # Lᵀ x = y
        x[r] = (y[r] - sum(L[i][r] * x[i] for i in range(r + 1, k))) / L[r][r]
    return jnp.stack(x)


def rigid_body_tensor(inertia, mass) -> Float[Array, "6 6"]:
    """`diag(J, m I)`: the 6×6 kinetic tensor of a body with its origin at the centre of mass."""
    inertia = jnp.asarray(inertia)
    if inertia.shape not in ((3,), (3, 3)):
        raise ValueError(
            f"`inertia` must be principal moments of shape (3,) or a tensor of shape (3, 3), "
            f"got shape {inertia.shape}."
        )
    if jnp.ndim(mass) != 0:
        raise ValueError(f"`mass` must be a scalar, got shape {jnp.shape(mass)}.")
    if is_concrete(mass):
        check_finite("mass", mass)
        if not float(mass) > 0:
            raise ValueError(f"`mass` must be > 0, got {float(mass)}.")
    J, tensor = _assembled(inertia, mass)
    check_spd("inertia", J)
    return tensor


@jax.jit
def _assembled(inertia, mass):
    """`(J, diag(J, m I))`, one compiled program (eagerly, each operation would be a small
    program of its own, compiled at its first call)."""
    J = jnp.diag(inertia) if inertia.ndim == 1 else inertia
    dtype = jnp.result_type(J, mass, float)
    zero = jnp.zeros((3, 3), dtype)
    top = jnp.concatenate([J.astype(dtype), zero], axis=1)
    bottom = jnp.concatenate([zero, jnp.asarray(mass, dtype) * jnp.eye(3, dtype=dtype)], axis=1)
    return J, jnp.concatenate([top, bottom], axis=0)


class RigidBodySE3(AbstractLieSystem):
    """A rigid body in space (rotation and translation), left-invariant on SE(3).

    Give either `inertia` and `mass` (a body in vacuum, body origin at the centre of
    mass) or the full kinetic tensor `tensor` (Kirchhoff's body in a fluid, or an origin
    away from the centre of mass):

    **Arguments:**

    - `inertia`: principal moments `(3,)` or a tensor `(3, 3)` about the centre of mass,
      body frame.
    - `mass`: the mass, a scalar `> 0`.
    - `tensor`: a symmetric positive definite `(6, 6)` tensor `M` in the twist order
      `(ω, v)`: `l(ξ) = ½ ξᵀ M ξ`. A pytree leaf, so `jax.grad` and `jax.vmap` reach it.
    - `potential`: `None` (free motion), a `lievi.AbstractPotential` of the 4×4 pose such
      as `lievi.UniformGravitySE3` or `lievi.CentralGravity`, or any callable `V(g)`.

    Momentum coordinates are `m = (Π, P)`: angular momentum about the body origin and
    linear momentum, both in the body frame. `lievi.diagnostics.spatial_momentum` gives
    the conserved spatial momentum `(RΠ + p × RP, RP)` and `lievi.diagnostics.casimirs`
    the Casimirs `(|P|², P·Π)`.
    """

    tensor: Float[Array, "6 6"]
    potential: AbstractPotential | None
    group: MatrixLieGroup = eqx.field(static=True)
    side: Side = eqx.field(static=True)

    def __init__(self, inertia=None, mass=None, *, tensor=None, potential=None):
        if tensor is None:
            if inertia is None or mass is None:
                raise ValueError(
                    "Give `inertia` and `mass` (a body in vacuum) or `tensor` (a 6×6 kinetic "
                    "tensor, e.g. with added mass)."
                )
            tensor = rigid_body_tensor(inertia, mass)
        elif inertia is not None or mass is not None:
            raise ValueError("Give either `tensor` or `inertia` and `mass`, not both.")
        self.tensor = tensor
        self.potential = as_potential(potential)
        self.group = SE3
        self.side = Side.LEFT

    def __check_init__(self):
        shape = jnp.shape(self.tensor)
        if shape != (6, 6):
            raise ValueError(
                f"`tensor` must be a (6, 6) kinetic tensor in the twist order (ω, v), got "
                f"shape {shape}."
            )

    def parameter_conditions(self):
        """A finite, symmetric, positive definite tensor (`spd_conditions`) whose inertia
        block is not singular to rounding (`regular_inertia`)."""
        finite, symmetric, positive = spd_conditions("tensor", self.tensor)
        regular = regular_inertia("inertia", jnp.asarray(self.tensor)[..., :3, :3])
        return super().parameter_conditions() + [finite, symmetric, regular, positive]

    def kinetic_tensor(self) -> Float[Array, "6 6"]:
        return self.tensor

    def lagrangian(self, xi: Float[Array, 6]) -> Scalar:
        return jnp.dot(xi, self.legendre(xi)) / 2

    def legendre(self, xi: Float[Array, 6]) -> Float[Array, 6]:
        return jnp.asarray(self.tensor) @ xi

    def velocity(self, m: Float[Array, 6]) -> Float[Array, 6]:
        return spd_solve(jnp.asarray(self.tensor, jnp.result_type(self.tensor, m)), m)

    def energy(self, m: Float[Array, 6]) -> Scalar:
        return jnp.dot(m, self.velocity(m)) / 2
