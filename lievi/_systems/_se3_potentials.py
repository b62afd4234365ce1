"""Gravity on a body that moves in space: potentials of the pose `g = [[R, p], [0, 1]]`.

- `UniformGravitySE3`: `V = m γ e₃·(p + Rρ)`, a body in free fall (a projectile that
  tumbles). Only rotations about, and translations along, the horizontal directions and
  the vertical axis leave `V` unchanged, so the horizontal linear momentum and the
  vertical angular momentum are conserved.
- `CentralGravity`: the Newtonian potential of a point mass (a planet, `μ = G M_planet`)
  at the world origin acting on a body made of point masses `m_i` at body positions `ρ_i`:
  `V = −μ Σ m_i / |p + R ρ_i|`. This is the **full body problem** of a rigid satellite
  (Maciejewski, Celest. Mech. 63 (1995); Lee, Leok & McClamroch, *Lie group variational
  integrators for the full body problem*, Comput. Methods Appl. Mech. Eng. 196 (2007)):
  the orbit and the attitude exchange energy and angular momentum through the gravity
  gradient. `V` is invariant under rotations about the origin, `V(h g) = V(g)` for
  `h = [[Q, 0], [0, 1]]`, so the total angular momentum about the planet, orbital plus
  spin, `RΠ + p × RP` (the first three components of
  `lievi.diagnostics.spatial_momentum`), is conserved — exactly by `lievi.DEP`, whose
  discrete Lagrangian has the same invariance (discrete Noether theorem, paper §2).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._potential import AbstractPotential
from ._se3_body import RigidBodySE3


class UniformGravitySE3(AbstractPotential):
    """Uniform gravity on a free body: `V(g) = m γ e₃·(p + R ρ)`.

    **Arguments:**

    - `mass`: the mass `m ≥ 0`.
    - `gravity`: the acceleration `γ` (default 9.81), along `−e₃` of the world.
    - `center_of_mass`: `ρ`, the centre of mass in the body frame, shape `(3,)`; default
      the body origin (then gravity exerts no torque).
    """

    mass: Float[Array, ""]
    gravity: Float[Array, ""]
    center_of_mass: Float[Array, 3]

    def __init__(self, mass, gravity=9.81, center_of_mass=None):
        self.mass = mass
        self.gravity = gravity
        self.center_of_mass = jnp.zeros(3) if center_of_mass is None else center_of_mass

    def __check_init__(self):
        for name in ("mass", "gravity"):
            if jnp.ndim(getattr(self, name)) != 0:
                raise ValueError(
                    f"`{name}` must be a scalar, got shape {jnp.shape(getattr(self, name))}."
                )
        if jnp.shape(self.center_of_mass) != (3,):
            raise ValueError(
                f"`center_of_mass` must have shape (3,) (body frame), got {jnp.shape(self.center_of_mass)}."
            )

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (jnp.asarray(self.mass) >= 0, "`mass` must be ≥ 0.")
        ]

    def __call__(self, g):
        height = jnp.dot(g[2, :3], self.center_of_mass) + g[2, 3]  # e₃·(Rρ + p)
        return self.mass * self.gravity * height

    def linear_coupling(self):
        # V = aᵀ g b with a = (e₃, 0), b = mγ (ρ, 1): the height of the centre of mass,
        # e₃·(Rρ + p). Its wrench is (Γ × mγρ, −mγΓ), Γ = Rᵀe₃ (the fast path of
        # `lievi.RKMK4` on SE(3)). No `advected_direction`: the reduced `(Π, Γ)` paths are
        # SO(3)'s.
        weight = jnp.asarray(self.mass) * jnp.asarray(self.gravity)
        a = jnp.array([0.0, 0.0, 1.0, 0.0])
        rho = jnp.asarray(self.center_of_mass)
        b = weight[..., None] * jnp.concatenate([rho, jnp.ones(rho.shape[:-1] + (1,))], -1)
        return a, b


class CentralGravity(AbstractPotential):
    """Newtonian gravity of a point mass at the world origin on a body of point masses.

    `V(g) = −μ Σ_i m_i / |p + R ρ_i|`.

    **Arguments:**

    - `mu`: the gravitational parameter `μ = G M` of the attracting body, `> 0`.
    - `masses`: the point masses `m_i > 0`, shape `(k,)`.
    - `points`: their body-frame positions `ρ_i`, shape `(k, 3)`.

    The positions are measured from the body origin; for `RigidBodySE3(inertia, mass)`
    (kinetic tensor `diag(J, m I)`) that origin must be the centre of mass,
    `Σ m_i ρ_i = 0` — `full_body_problem` builds such a body.
    """

    mu: Float[Array, ""]
    masses: Float[Array, " k"]
    points: Float[Array, "k 3"]

    def __check_init__(self):
        if jnp.ndim(self.mu) != 0:
            raise ValueError(f"`mu` must be a scalar, got shape {jnp.shape(self.mu)}.")
        k = jnp.shape(self.masses)
        if len(k) != 1 or jnp.shape(self.points) != (k[0], 3):
            raise ValueError(
                f"`masses` must have shape (k,) and `points` shape (k, 3), got {k} and "
                f"{jnp.shape(self.points)}."
            )

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (jnp.asarray(self.mu) > 0, "`mu` must be > 0."),
            (jnp.all(jnp.asarray(self.masses) > 0), "`masses` must all be > 0."),
        ]

    def __call__(self, g):
        positions = jnp.asarray(self.points) @ g[:3, :3].T + g[:3, 3]  # p + R ρ_i
        distances = jnp.sqrt(jnp.sum(positions**2, axis=-1))
        return -self.mu * jnp.sum(jnp.asarray(self.masses) / distances)


@jax.jit  # one compiled program: eagerly, each operation would be one, compiled at first use
def point_mass_body(masses: Float[Array, " k"], points: Float[Array, "k 3"]):
    """`(mass, centred points, inertia)` of a rigid body made of point masses: the total
    mass, the points measured from their centre of mass, and the inertia tensor about it,
    `Σ m_i (|ρ_i|² I − ρ_i ρ_iᵀ)`."""
    mass = jnp.sum(masses)
    # Points of mass 0 (padding: `lievi.gravitating_bodies` of bodies of different sizes)
    # are put at the centre of mass; they add nothing to the mass or the inertia.
    centered = jnp.where(masses[:, None] > 0, points - masses @ points / mass, 0.0)
    squared = jnp.sum(centered**2, axis=-1)
    inertia = jnp.einsum(
        "i,ijk->jk",
        masses,
        squared[:, None, None] * jnp.eye(3) - centered[:, :, None] * centered[:, None, :],
    )
    return mass, centered, inertia


def full_body_problem(mu, masses, points, extra_inertia=None) -> RigidBodySE3:
    """A rigid satellite of point masses orbiting a planet: `RigidBodySE3` + `CentralGravity`.

    The points are shifted to their centre of mass (the body origin). The inertia about
    it is `Σ m_i (|ρ_i|² I − ρ_i ρ_iᵀ)` plus `extra_inertia` (a `(3, 3)` tensor, e.g. for
    a dumbbell, whose point-mass inertia is singular along its axis).

    **Arguments:** `mu` (`G M` of the planet), `masses` `(k,)`, `points` `(k, 3)`,
    `extra_inertia` (optional, `(3, 3)`).

    **Returns:** `RigidBodySE3(inertia, mass, potential=CentralGravity(mu, masses, ρ))`.
    """
    masses, points = jnp.asarray(masses), jnp.asarray(points)
    if masses.ndim != 1 or points.shape != (masses.shape[0], 3):
        raise ValueError(
            f"`masses` must have shape (k,) and `points` shape (k, 3), got {masses.shape} and "
            f"{points.shape}."
        )
    mass, centered, inertia = point_mass_body(masses, points)
    if extra_inertia is not None:
        inertia = inertia + jnp.asarray(extra_inertia)
    return RigidBodySE3(inertia, mass, potential=CentralGravity(mu, masses, centered))
