"""Coupling potentials of N rigid bodies, functions of the poses `g` `(N, 4, 4)`.

Each body carries point sites at fixed body-frame positions `s_ia`; their world positions
are `x_ia = R_i s_ia + p_i`. The potentials below depend on the poses only through the
distances `|x_ia − x_jb|` between sites of different bodies, which a common rigid motion
of all bodies leaves unchanged: they are invariant under the diagonal action of SE(3),
so the total linear and angular momentum are conserved (`lievi.RigidBodies`). Pairs of
sites on one body are excluded (their distance is fixed: a constant energy).

- `SitePotential`: a pair energy (`lievi.LennardJones`, `lievi.Coulomb`, `lievi.Morse`,
  or several summed) over every pair of sites on different bodies — rigid molecules;
- `SiteSprings`: springs between named sites — formations, tethers;
- `MutualGravity`: Newtonian gravity between point-mass sets — the full body problem of
  extended bodies modelled as point masses (`gravitating_bodies` builds the system).

The torques and forces on each body are the derivatives of these energies along each
body's own motions, by autodiff (`AbstractLieSystem.force`). A pair of sites that
coincide gives an infinite energy (or a non-finite force), which `simulate` reports as
`RESULTS.nonfinite`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._checks import is_concrete
from ._pair_energies import AbstractPairEnergy
from ._potential import AbstractPotential
from ._rigid_bodies import RigidBodies
from ._se3_potentials import point_mass_body


def site_positions(g: Float[Array, "N 4 4"], sites: Float[Array, "N k 3"]):
    """The world positions `R_i s_ia + p_i` of the body-frame sites, shape `(N, k, 3)`."""
    return jnp.einsum("nij,nkj->nki", g[:, :3, :3], sites) + g[:, None, :3, 3]


def cross_body_pairs(n_bodies: int, n_sites: int):
    """Index arrays `(i, j)`, `i < j`, of the flattened sites (body-major) that lie on
    different bodies: every pair once, none within a body. NumPy, fixed by the shapes."""
    i, j = np.triu_indices(n_bodies * n_sites, k=1)
    keep = i // n_sites != j // n_sites
    return i[keep], j[keep]


def _check_sites(sites, per_site: dict) -> None:
    shape = jnp.shape(sites)
    if len(shape) != 3 or shape[-1] != 3:
        raise ValueError(
            f"`sites` must have shape (N, k, 3) (k body-frame positions per body), got {shape}."
        )
    for name, value in per_site.items():
        if value is not None and jnp.shape(value) != shape[:2]:
            raise ValueError(
                f"`{name}` must have shape (N, k) = {shape[:2]}, one per site, got "
                f"{jnp.shape(value)}."
            )


def _distances(g, sites):
    """`(r, i, j)`: the distances of the sites on different bodies, and the pairs' flat
    site indices."""
    n, k = jnp.shape(sites)[:2]
    x = site_positions(g, jnp.asarray(sites, g.dtype)).reshape(n * k, 3)
    i, j = cross_body_pairs(n, k)
    d = x[i] - x[j]
    return jnp.sqrt(jnp.sum(d * d, axis=-1)), i, j


class SitePotential(AbstractPotential):
    """`V(g) = Σ e(|x_ia − x_jb|)` over every pair of sites on different bodies.

    **Arguments:**

    - `sites`: body-frame positions `(N, k, 3)`, measured from each body's centre of mass.
    - `pair`: a pair energy (`lievi.LennardJones`, `lievi.Coulomb`, `lievi.Morse`) or a
      tuple of them (summed).
    - `types`: integer site types `(N, k)` (default all 0), indexing the `(T, T)`
      parameter tables of the pair energies.
    - `charges`: site charges `(N, k)`, for `lievi.Coulomb`.

    Cost: one evaluation of `e` per pair, `N k (N − 1) k / 2` pairs (all pairs, no
    cut-off or neighbour list).
    """

    sites: Float[Array, "N k 3"]
    pair: tuple[AbstractPairEnergy, ...]
    types: Int[Array, "N k"]
    charges: Float[Array, "N k"] | None

    def __init__(self, sites, pair, types=None, charges=None):
        self.sites = jnp.asarray(sites, float)
        self.pair = tuple(pair) if isinstance(pair, (tuple, list)) else (pair,)
        shape = jnp.shape(self.sites)[:2]
        self.types = jnp.zeros(shape, int) if types is None else jnp.asarray(types)
        self.charges = None if charges is None else jnp.asarray(charges, float)

    def __check_init__(self):
        _check_sites(self.sites, {"types": self.types, "charges": self.charges})
        if not jnp.issubdtype(self.types.dtype, jnp.integer):
            raise ValueError(f"`types` must be integers, got dtype {self.types.dtype}.")
        for energy in self.pair:
            if not isinstance(energy, AbstractPairEnergy):
                raise ValueError(
                    "`pair` must be a pair energy (lievi.LennardJones, lievi.Coulomb, "
                    f"lievi.Morse) or a tuple of them, got {type(energy).__name__}."
                )
            if energy.needs_charges() and self.charges is None:
                raise ValueError(
                    f"{type(energy).__name__} reads the sites' charges: pass `charges` (N, k)."
                )
            if is_concrete(self.types):
                largest = int(jnp.max(self.types)) if self.types.size else 0
                if int(jnp.min(self.types)) < 0:
                    raise ValueError("`types` must be ≥ 0 (indices into the pair tables).")
                for name, table in energy.tables().items():
                    if largest >= jnp.shape(table)[0]:
                        raise ValueError(
                            f"{type(energy).__name__}.{name} is a table over "
                            f"{jnp.shape(table)[0]} site types, but `types` uses type "
                            f"{largest}: give a ({largest + 1}, {largest + 1}) table or fix "
                            "`types`."
                        )

    def parameter_conditions(self):
        conditions = super().parameter_conditions()
        for energy in self.pair:
            conditions = conditions + energy.parameter_conditions()
        return conditions

    def __call__(self, g):
        r, i, j = _distances(g, self.sites)
        types = self.types.reshape(-1)
        charges = (
            jnp.zeros(types.shape, g.dtype) if self.charges is None else self.charges.reshape(-1)
        )
        return sum(jnp.sum(e(r, types[i], types[j], charges[i], charges[j])) for e in self.pair)


class SiteSprings(AbstractPotential):
    """Springs between named sites of different bodies: `V = Σ_s ½ k_s (|x_a − x_b| − L_s)²`.

    **Arguments:**

    - `sites`: body-frame positions `(N, k, 3)`.
    - `pairs`: integers `(S, 4)`, each row `(body_a, site_a, body_b, site_b)`, `body_a ≠
      body_b`.
    - `stiffness`: `k_s ≥ 0`, a scalar or `(S,)`.
    - `rest_length`: `L_s ≥ 0`, a scalar or `(S,)` (default 0).
    """

    sites: Float[Array, "N k 3"]
    pairs: Int[Array, "S 4"]
    stiffness: Float[Array, ...]
    rest_length: Float[Array, ...]

    def __init__(self, sites, pairs, stiffness, rest_length=0.0):
        self.sites = jnp.asarray(sites, float)
        self.pairs = jnp.asarray(pairs)
        self.stiffness = jnp.asarray(stiffness, float)
        self.rest_length = jnp.asarray(rest_length, float)

    def __check_init__(self):
        _check_sites(self.sites, {})
        n, k = jnp.shape(self.sites)[:2]
        pairs = self.pairs
        if pairs.ndim != 2 or pairs.shape[1] != 4 or not jnp.issubdtype(pairs.dtype, jnp.integer):
            raise ValueError(
                "`pairs` must be integers of shape (S, 4), rows (body_a, site_a, body_b, "
                f"site_b), got shape {pairs.shape} and dtype {pairs.dtype}."
            )
        for name in ("stiffness", "rest_length"):
            value = getattr(self, name)
            if jnp.ndim(value) != 0 and jnp.shape(value) != (pairs.shape[0],):
                raise ValueError(
                    f"`{name}` must be a scalar or have shape ({pairs.shape[0]},), one per "
                    f"spring, got {jnp.shape(value)}."
                )
        if is_concrete(pairs) and pairs.size:
            p = np.asarray(pairs)
            bad = (p < 0) | (p >= np.array([n, k, n, k]))
            if bad.any():
                raise ValueError(
                    f"`pairs` row {int(np.argmax(bad.any(axis=1)))} names a body or site "
                    f"outside the {n} bodies of {k} sites."
                )
            if (p[:, 0] == p[:, 2]).any():
                raise ValueError(
                    f"`pairs` row {int(np.argmax(p[:, 0] == p[:, 2]))} joins two sites of one "
                    "body (their distance is fixed): join sites of different bodies."
                )

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (jnp.all(self.stiffness >= 0), "`stiffness` must be ≥ 0."),
            (jnp.all(self.rest_length >= 0), "`rest_length` must be ≥ 0."),
        ]

    def __call__(self, g):
        x = site_positions(g, jnp.asarray(self.sites, g.dtype))
        d = x[self.pairs[:, 0], self.pairs[:, 1]] - x[self.pairs[:, 2], self.pairs[:, 3]]
        squared = jnp.sum(d * d, axis=-1)
        # A spring of rest length 0 may pass through zero length: its energy ½k|d|² is
        # smooth there, but √ is not (both branches of `where` are differentiated).
        positive = squared > 0
        length = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)
        return jnp.sum(self.stiffness * (length - self.rest_length) ** 2) / 2


class MutualGravity(AbstractPotential):
    """Newtonian gravity between bodies made of point masses:
    `V(g) = −G Σ m_ia m_jb / |x_ia − x_jb|` over pairs of points on different bodies.

    **Arguments:**

    - `G`: the gravitational constant of the units in use, `> 0`.
    - `masses`: the point masses `(N, k)`, `> 0`.
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
        _check_sites(self.points, {"masses": self.masses})

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (self.G > 0, "`G` must be > 0."),
            (jnp.all(self.masses > 0), "`masses` must all be > 0."),
        ]

    def __call__(self, g):
        r, i, j = _distances(g, self.points)
        masses = jnp.asarray(self.masses, g.dtype).reshape(-1)
        return -self.G * jnp.sum(masses[i] * masses[j] / r)


def gravitating_bodies(G, masses, points, extra_inertia=None) -> RigidBodies:
    """N rigid bodies of point masses in mutual gravity (the full N-body problem).

    Each body's points are shifted to their centre of mass (the body origin); its mass is
    their sum and its inertia `Σ m_a (|ρ_a|² I − ρ_a ρ_aᵀ)` plus `extra_inertia` (a
    `(N, 3, 3)` array, e.g. for a dumbbell, whose point-mass inertia is singular).

    **Arguments:** `G`, `masses` `(N, k)`, `points` `(N, k, 3)`, `extra_inertia`
    (optional).

    **Returns:** `RigidBodies(inertia, mass, potential=MutualGravity(G, masses, ρ))`.
    """
    masses, points = jnp.asarray(masses, float), jnp.asarray(points, float)
    _check_sites(points, {"masses": masses})
    mass, centered, inertia = jax.vmap(point_mass_body)(masses, points)
    if extra_inertia is not None:
        inertia = inertia + jnp.asarray(extra_inertia)
    potential = MutualGravity(G, masses, centered)
    return RigidBodies(inertia, mass, potential=potential)
