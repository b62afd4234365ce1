"""Potentials `V(g)` on the group: the systems of the paper's §7 (broken symmetry).

With a potential the Lagrangian is `L(g, ξ) = l(ξ) − V(g)`: it is invariant only under the
subgroup that leaves `V` unchanged (for gravity: rotations about the vertical, `G^[ζ]` of
§7 with the advected parameter `ζ` the vertical direction). The integrators see `V` only
through its value (energy, discrete Lagrangian) and through the generalised force

    M(g) = −d/dε V(g exp(ε e_i)) |_{ε=0}      (left-invariant systems; `exp(ε e_i) g` for right),

the derivative of `V` trivialised on the side of the symmetry, computed by autodiff
(`AbstractLieSystem.force`): a potential is just a scalar function, with no hand-written
gradient. For the rigid body `M` is the body-frame torque.
"""

from __future__ import annotations

import abc
from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._checks import Conditions, finite_conditions, is_concrete, raise_if_violated


class AbstractPotential(eqx.Module):
    """A potential energy `V(g)` of a group element `g` (an `(n, n)` matrix).

    Subclass it and implement `__call__`; array fields are pytree leaves, so `jax.grad`
    and `jax.vmap` reach the potential's parameters (e.g. to identify them from data).
    `V` must be a differentiable function of the matrix entries near the group: the force
    is its derivative along the group's tangent directions.
    """

    def __check_init__(self):
        # After the subclass's own checks (shapes, dtypes): the parameter values, eagerly.
        raise_if_violated(self.parameter_conditions)

    @abc.abstractmethod
    def __call__(self, g: Float[Array, "n n"]) -> Scalar:
        """The potential energy at `g`."""

    def parameter_conditions(self) -> Conditions:
        """The admissible parameters, as conditions (`lievi._checks.Conditions`): here
        every floating-point array finite; subclasses add theirs (a mass `≥ 0`, …). One
        definition for both forms: the constructor raises on a concrete violation, and a
        system's `parameters_valid` includes them traced (`RESULTS.invalid_input`)."""
        return finite_conditions(self)

    def advected_direction(self) -> Float[Array, " n"] | None:
        """The fixed spatial vector `a` if `V` depends on `g` only through the advected
        parameter `Γ = gᵀa` (the paper's §7: the symmetry is broken to the subgroup
        `G^[a]` that fixes `a`), else `None` (the default).

        For such a potential the left-invariant dynamics closes on `(Π, Γ)`: with
        `F_k = g_k⁻¹g_{k+1}` the step's relative rotation, `Γ_{k+1} = F_kᵀΓ_k` (the
        Bobenko–Suris reduced discrete Lie–Poisson equations), so `g` need not be carried
        (`simulate_batch` does so when `g` is not saved).
        """
        return None

    def advected(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n"] | None:
        """The advected parameter `Γ = gᵀa` (`a = advected_direction()`), for any leading
        axes of `g`, or `None` where the potential has none."""
        a = self.advected_direction()
        if a is None:
            return None
        return jnp.einsum("i,...ij->...j", jnp.asarray(a, jnp.result_type(g, float)), g)

    def value_and_body_wrenches(self, g: Float[Array, "N 4 4"]) -> tuple | None:
        """For a potential of N rigid bodies' poses (`lievi.RigidBodies`): `(V(g), M(g))`
        with `M` `(N, 6)` each body's generalised force `−dV` along `g_i exp(ε ξ)` (torque,
        force; as `AbstractLieSystem.force`), in closed form — or `None` (the default:
        the force is the reverse-mode derivative of `V`). A potential that sums over many
        pairs of sites gives it where one forward pass of the pair terms is cheaper than a
        reverse pass through them (`lievi.SitePotential`)."""
        return None

    def linear_coupling(self) -> tuple[Float[Array, " n"], Float[Array, " n"]] | None:
        """`(a, b)` if the potential is linear in `g`, `V(g) = aᵀ g b` (a fixed spatial
        vector `a`, a body vector `b`), else `None` (the default).

        Such a potential depends on `g` only through the advected parameter `Γ = gᵀa`
        (`advected_direction` is `a`), and on a rigid body its torque has the closed form
        `M = Γ × b` (`V(g exp(εξ)) = aᵀg(1 + εξ̂)b`, so `dV·ξ = Γ·(ξ × b)`): the fast
        batched steps of the methods with a kick use it. Uniform gravity is the example:
        `a = e_z`, `b = m γ ρ`. On SE(3) `a`, `b` are 4-vectors (`UniformGravitySE3`:
        `a = (e_z, 0)`, `b = m γ (ρ, 1)`), the wrench `(Γ × b₃, −b₄Γ)` with `Γ = Rᵀa₃`.
        """
        return None


class PotentialFunction(AbstractPotential):
    """A potential given as any callable `fn(g) -> scalar`.

    `fn` may be a plain function or an `eqx.Module` (e.g. an `eqx.nn.MLP` of the matrix
    entries); in the latter case its parameters are pytree leaves of the system.
    """

    fn: Callable[[Float[Array, "n n"]], Scalar]

    def __call__(self, g):
        return self.fn(g)


class UniformGravity(AbstractPotential):
    """Uniform gravity on a body with a fixed point: `V(g) = m·γ·e_z·(g ρ)`.

    `g` maps body coordinates to world coordinates, the world's vertical is its last axis
    `e_z` (`e₃` on SO(3)), and `ρ` is the centre of mass in the body frame, measured from
    the fixed point. The potential depends on `g` only through the body-frame vertical
    `Γ = gᵀ e_z` (`V = m γ ρ·Γ`): the advected parameter of the paper's §7. The body torque
    is `M = m γ Γ × ρ` on SO(3). With the inertia taken about the fixed point this is the
    heavy top (and, for a long arm, the 3-D pendulum).

    **Arguments:**

    - `mass`: the mass `m ≥ 0`.
    - `center_of_mass`: `ρ`, shape `(n,)` (the body frame; `(3,)` on SO(3)).
    - `gravity`: the acceleration `γ` (default 9.81; pass 1 for nondimensional units).

    Only the product `m ρ` enters the dynamics; `mass` and `center_of_mass` are separate
    leaves for readability.
    """

    mass: Float[Array, ""]
    center_of_mass: Float[Array, " n"]
    gravity: Float[Array, ""]

    def __init__(self, mass, center_of_mass, gravity=9.81):
        self.mass = mass
        self.center_of_mass = center_of_mass
        self.gravity = gravity

    def __check_init__(self):
        if jnp.ndim(self.mass) != 0:
            raise ValueError(f"`mass` must be a scalar, got shape {jnp.shape(self.mass)}.")
        if jnp.ndim(self.gravity) != 0:
            raise ValueError(f"`gravity` must be a scalar, got shape {jnp.shape(self.gravity)}.")
        if jnp.ndim(self.center_of_mass) != 1:
            raise ValueError(
                "`center_of_mass` must be a vector in the body frame, shape (n,), got shape "
                f"{jnp.shape(self.center_of_mass)}."
            )
        for name in ("mass", "center_of_mass", "gravity"):
            value = getattr(self, name)
            if is_concrete(value) and not np.isrealobj(np.asarray(value)):
                raise ValueError(f"`{name}` must be real, got {np.asarray(value).dtype}.")

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (jnp.asarray(self.mass) >= 0, "`mass` must be ≥ 0.")
        ]

    def __call__(self, g):
        rho = jnp.asarray(self.center_of_mass)
        return self.mass * self.gravity * jnp.dot(g[-1], rho)  # e_z·(g ρ) = (gᵀ e_z)·ρ

    def advected_direction(self):
        # V = mγ ρ·(gᵀe_z): the world's vertical e_z is advected.
        n = jnp.shape(self.center_of_mass)[-1]
        return jnp.zeros(n).at[-1].set(1.0)

    def linear_coupling(self):
        # V = e_zᵀ g (mγρ); the torque is M = Γ × mγρ (the heavy top's).
        mass, gravity = jnp.asarray(self.mass), jnp.asarray(self.gravity)
        return self.advected_direction(), (mass * gravity)[..., None] * self.center_of_mass

    def vertical(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n"]:
        """The advected parameter `Γ = gᵀ e_z`: the world's vertical in body coordinates."""
        return g[..., -1, :]


def as_potential(potential) -> AbstractPotential | None:
    """`None`, an `AbstractPotential`, or any callable `V(g)` (wrapped); else an error."""
    if potential is None or isinstance(potential, AbstractPotential):
        return potential
    if callable(potential):
        return PotentialFunction(potential)
    raise ValueError(
        "`potential` must be None, a lievi.AbstractPotential (e.g. lievi.UniformGravity) or a "
        f"callable V(g) returning a scalar, got {type(potential).__name__}."
    )
