"""Newtonian gravity between rigid bodies made of point masses: `MutualGravity` and
`gravitating_bodies`, the full body problem of extended bodies modelled as point masses.
Like the site couplings (`_couplings.py`), a function of distances between points of
different bodies: invariant under the diagonal action of SE(3)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._couplings import check_sites, cross_body_pairs, site_positions, site_wrenches
from ._potential import AbstractPotential
from ._ragged import stack_bodies
from ._rigid_bodies import RigidBodies
from ._se3_potentials import point_mass_body


class MutualGravity(AbstractPotential):
    """Newtonian gravity between bodies made of point masses:
    `V(g) = −G Σ m_ia m_jb / |x_ia − x_jb|` over pairs of points on different bodies.

    **Arguments:**

    - `G`: the gravitational constant of the units in use, `> 0`.
    - `masses`: the point masses `(N, k)`, `≥ 0`, each body's sum `> 0`. A point of mass
      0 takes part in no pair: bodies of fewer than `k` points are padded with such points
      (`gravitating_bodies` pads a list of bodies of different sizes).
    - `points`: their body-frame positions `(N, k, 3)`, measured from each body's centre
      of mass (`gravitating_bodies` shifts them there).

    As a model of extended bodies this is a quadrature of the mutual potential: exact for
    the point masses themselves, and for continuous bodies correct up to the moments the
    points reproduce. Points with each body's mass, centre of mass and inertia tensor (as
    `gravitating_bodies` gives them) reproduce its monopole and quadrupole, so the
    error in `V` is of relative order `(ℓ/r)³` for bodies of size `ℓ` at distance `r`.
    """

    G: Float[Array, ""]
    masses: Float[Array, "N k"]
    points: Float[Array, "N k 3"]

    def __init__(self, G, masses, points):
        self.G = jnp.asarray(G, float)
        self.masses = jnp.asarray(masses, float)
        self.points = jnp.asarray(points, float)

    def __check_init__(self):
        if jnp.ndim(self.G) != 0:
            raise ValueError(f"`G` must be a scalar, got shape {jnp.shape(self.G)}.")
        check_sites(self.points, {"masses": self.masses})

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (self.G > 0, "`G` must be > 0."),
            (
                jnp.all(self.masses >= 0),
                "`masses` must all be ≥ 0 (0: a padding point, in no pair).",
            ),
            (
                jnp.all(jnp.any(self.masses > 0, axis=-1)),
                "`masses` must give each body a point of mass > 0.",
            ),
        ]

    def __call__(self, g):
        n, k = jnp.shape(self.points)[:2]
        x = site_positions(g, jnp.asarray(self.points, g.dtype)).reshape(n * k, 3)
        i, j = cross_body_pairs(n, k)
        masses = jnp.asarray(self.masses, g.dtype).reshape(-1)
        product = masses[i] * masses[j]
        d = x[i] - x[j]
        # A padding point (mass 0) may sit anywhere, on another body's point too: its
        # pairs take the distance 1 before the square root (both branches of `where` are
        # differentiated), then count 0.
        real = product > 0
        r = jnp.sqrt(jnp.where(real, jnp.sum(d * d, axis=-1), 1.0))
        return -self.G * jnp.sum(jnp.where(real, product / r, 0.0))

    def value_and_body_wrenches(self, g):
        """`V(g)` and each body's wrench `(N, 6)` in closed form (`site_wrenches`): the force
        on point `a` is `f_a = −G Σ_b m_a m_b (x_a − x_b)/|x_a − x_b|³` over the points `b`
        of the other bodies. Every ordered pair of points at once, `(Nk, Nk)` (each pair
        twice, `V` halved; pairs within a body and with a point of mass 0 weighed 0): no
        gather of the pair list and no reverse pass through it. In a binary's splitting
        step (256 binaries, `benchmarks/compile_time.py`) the autodiff force was 180 of
        the step program's 1750 operations."""
        n, k = jnp.shape(self.points)[:2]
        dtype = jnp.result_type(g, float)
        x = site_positions(g, jnp.asarray(self.points, dtype)).reshape(n * k, 3)
        body = np.repeat(np.arange(n), k)
        masses = jnp.asarray(self.masses, dtype).reshape(-1)
        product = masses[:, None] * masses[None, :]
        real = (body[:, None] != body[None, :]) & (product > 0)
        d = x[:, None, :] - x[None, :, :]
        # Pairs not counted take the distance 1 (both branches of `where` are differentiated).
        inverse = 1 / jnp.sqrt(jnp.where(real, jnp.sum(d * d, axis=-1), 1.0))
        pull = jnp.where(real, product * inverse, 0.0)  # m_a m_b / r
        forces = -self.G * jnp.einsum("ab,abj->aj", pull * inverse * inverse, d)
        points = jnp.asarray(self.points, dtype)
        return -self.G / 2 * jnp.sum(pull), site_wrenches(g, points, forces.reshape(n, k, 3))


def gravitating_bodies(G, masses, points, extra_inertia=None) -> RigidBodies:
    """N rigid bodies of point masses in mutual gravity (the full N-body problem).

    Each body's points are shifted to their centre of mass (the body origin); its mass is
    their sum and its inertia `Σ m_a (|ρ_a|² I − ρ_a ρ_aᵀ)` plus `extra_inertia` (a
    `(N, 3, 3)` array, e.g. for a dumbbell, whose point-mass inertia is singular).

    **Arguments:** `G`, `masses` `(N, k)`, `points` `(N, k, 3)`, `extra_inertia`
    (optional). Bodies of different numbers of points: `masses` a list of `N` arrays
    `(k_i,)` and `points` a list of `(k_i, 3)`; they are padded to `k = max k_i` with
    points of mass 0 at the centre of mass, which take part in no pair (`MutualGravity`).

    **Returns:** `RigidBodies(inertia, mass, potential=MutualGravity(G, masses, ρ))`.
    """
    masses, given = stack_bodies("masses", masses, 0.0)
    points, given_points = stack_bodies("points", points, 0.0, (3,))
    check_sites(points, {"masses": masses})
    if not np.array_equal(given, given_points):
        raise ValueError(
            "`masses` and `points` must give each body as many masses as points, got "
            f"{given.sum(axis=1).tolist()} and {given_points.sum(axis=1).tolist()}."
        )
    mass, centered, inertia = jax.vmap(point_mass_body)(masses, points)
    if extra_inertia is not None:
        inertia = inertia + jnp.asarray(extra_inertia)
    potential = MutualGravity(G, masses, centered)
    return RigidBodies(inertia, mass, potential=potential)
