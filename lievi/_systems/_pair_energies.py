"""Pair energies `e(r)` of two point sites at distance `r`: the terms of a site potential.

Each is an `eqx.Module` whose parameters are pytree leaves (so `jax.grad` reaches `ε`,
`σ`, charges, …) and is called as `energy(r, type_i, type_j, charge_i, charge_j)` on
arrays of site pairs. A parameter may be a scalar (every pair of site types alike) or a
table `(T, T)` indexed by the two sites' types (`lievi.SitePotential(types=…)`), e.g.
the Lennard-Jones `ε` and `σ` of oxygen–oxygen, oxygen–hydrogen and hydrogen–hydrogen.
`value_and_slope(r², …)` gives `e` and `e'(r)/r` together from the squared distance, the
form `lievi.SitePotential`'s force pass uses.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._checks import Conditions, finite_conditions, raise_if_violated, shown


def _by_type(value, type_i, type_j):
    """A scalar parameter, or the entry `[type_i, type_j]` of a `(T, T)` table."""
    value = jnp.asarray(value)
    return value if value.ndim == 0 else value[type_i, type_j]


class AbstractPairEnergy(eqx.Module):
    """The energy of a pair of sites on different bodies as a function of their distance."""

    @abc.abstractmethod
    def __call__(self, r, type_i, type_j, charge_i, charge_j) -> Float[Array, ...]:
        """`e(r)` for arrays of pairs (their distances, types and charges)."""

    def value_and_slope(self, r2, type_i, type_j, charge_i, charge_j):
        """`(e(r), e'(r)/r)` at the squared distances `r2`: the energy and the factor of
        the pull `−(e'(r)/r) d` on a pair's first site (`d` its separation), both from
        `r²`, which is what a site pass computes. Broadcasts: a scalar `r2` with per-pair
        types or charges gives per-pair values. The default takes `√r2` and `e'` by
        forward-mode autodiff; the energies below give it in closed form, sharing `1/r²`
        (Lennard-Jones) or one reciprocal square root (Coulomb) between the two."""
        r = jnp.sqrt(r2)
        e, slope = jax.jvp(
            lambda r: self(r, type_i, type_j, charge_i, charge_j), (r,), (jnp.ones_like(r),)
        )
        return e, slope / r

    def tables(self) -> dict[str, Array]:
        """The parameters given per pair of site types (`(T, T)` tables), by name."""
        return {
            name: value
            for name, value in vars(self).items()
            if eqx.is_array(value) and jnp.ndim(value) == 2
        }

    def needs_charges(self) -> bool:
        """Whether the energy reads the sites' charges (`lievi.SitePotential(charges=…)`)."""
        return False

    def __check_init__(self):
        for name, value in vars(self).items():
            if eqx.is_array(value) and jnp.ndim(value) not in (0, 2):
                raise ValueError(
                    f"`{name}` must be a scalar or a (T, T) table over the site types, got "
                    f"shape {jnp.shape(value)}."
                )
            if jnp.ndim(value) == 2 and jnp.shape(value)[0] != jnp.shape(value)[1]:
                raise ValueError(
                    f"`{name}` must be a square (T, T) table over the site types, got shape "
                    f"{jnp.shape(value)}."
                )
        # After the shapes: the parameter values, eagerly (traced ones in `parameters_valid`).
        raise_if_violated(self.parameter_conditions)

    def parameter_conditions(self) -> Conditions:
        """Finite parameters, and each table symmetric (to 1e-10 relative, as
        `lievi._checks.spd_conditions`): the energy of a pair of sites of types `a`, `b`
        must not depend on which is listed first — the order of the bodies, or of a
        neighbour list's columns, would change it."""
        conditions = finite_conditions(self)
        for name, table in self.tables().items():
            asymmetry = jnp.max(jnp.abs(table - table.T))
            conditions.append(
                (
                    asymmetry <= 1e-10 * jnp.max(jnp.abs(table)),
                    f"`{name}` must be symmetric (`{name}[a, b]` is the parameter of a pair of "
                    f"types a and b, either way round){shown(asymmetry, ', off by {:.3g}')}; "
                    f"symmetrise it as ({name} + {name}.T)/2.",
                )
            )
        return conditions


class LennardJones(AbstractPairEnergy):
    """`e(r) = 4ε((σ/r)¹² − (σ/r)⁶)`; `epsilon` (`ε ≥ 0`), `sigma` (`σ > 0`): scalars or
    `(T, T)` tables over the site types."""

    epsilon: Float[Array, ...]
    sigma: Float[Array, ...]

    def __init__(self, epsilon=1.0, sigma=1.0):
        self.epsilon = jnp.asarray(epsilon, float)
        self.sigma = jnp.asarray(sigma, float)

    def __call__(self, r, type_i, type_j, charge_i, charge_j):
        s6 = (_by_type(self.sigma, type_i, type_j) / r) ** 6
        return 4 * _by_type(self.epsilon, type_i, type_j) * (s6 * s6 - s6)

    def value_and_slope(self, r2, type_i, type_j, charge_i, charge_j):
        """In `1/r²` alone: `s⁶ = (σ²/r²)³`, `e = 4ε(s¹² − s⁶)`, `e'/r = −24ε(2s¹² − s⁶)/r²`.
        `1/r²` is taken as `(1/√r²)²`: the reciprocal square root of `r²` is the one
        `Coulomb` and the cut-off's shift (`shifted_force`) take, so a site potential
        that has either computes it once per pair (the compiler merges the three), where
        a division of its own was a further pass over the pairs (7 % of the force of 64
        rigid water molecules)."""
        root = jax.lax.rsqrt(r2)
        inverse = root * root
        sigma = _by_type(self.sigma, type_i, type_j)
        s2 = sigma * sigma * inverse
        s6 = s2 * s2 * s2
        four_epsilon = 4 * _by_type(self.epsilon, type_i, type_j)
        return four_epsilon * (s6 * s6 - s6), -6 * four_epsilon * (2 * s6 * s6 - s6) * inverse

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (jnp.all(self.epsilon >= 0), "`epsilon` must be ≥ 0."),
            (jnp.all(self.sigma > 0), "`sigma` must be > 0."),
        ]


class Coulomb(AbstractPairEnergy):
    """`e(r) = k q_i q_j / √(r² + s²)`: Coulomb's energy of the sites' charges, softened
    by the length `softening` `s ≥ 0` (`0`: the bare `1/r`). `k` (default 1) is the
    Coulomb constant of the units in use."""

    k: Float[Array, ""]
    softening: Float[Array, ""]

    def __init__(self, k=1.0, softening=0.0):
        self.k = jnp.asarray(k, float)
        self.softening = jnp.asarray(softening, float)

    def __check_init__(self):
        for name in ("k", "softening"):
            if jnp.ndim(getattr(self, name)) != 0:
                raise ValueError(
                    f"`{name}` must be a scalar, got {jnp.shape(getattr(self, name))}."
                )

    def needs_charges(self):
        return True

    def __call__(self, r, type_i, type_j, charge_i, charge_j):
        return self.k * charge_i * charge_j / jnp.sqrt(r * r + self.softening**2)

    def value_and_slope(self, r2, type_i, type_j, charge_i, charge_j):
        """One reciprocal square root `u = 1/√(r² + s²)`: `e = k q_i q_j u`,
        `e'/r = −e u²`."""
        u = jax.lax.rsqrt(r2 + self.softening**2)
        e = self.k * charge_i * charge_j * u
        return e, -e * u * u

    def parameter_conditions(self):
        return super().parameter_conditions() + [(self.softening >= 0, "`softening` must be ≥ 0.")]


class Morse(AbstractPairEnergy):
    """`e(r) = D (e^{−2a(r − r₀)} − 2 e^{−a(r − r₀)})`, the Morse bond: depth `depth`
    (`D ≥ 0`), stiffness `width` (`a > 0`), equilibrium distance `r0`; scalars or `(T, T)`
    tables over the site types."""

    depth: Float[Array, ...]
    width: Float[Array, ...]
    r0: Float[Array, ...]

    def __init__(self, depth=1.0, width=1.0, r0=1.0):
        self.depth = jnp.asarray(depth, float)
        self.width = jnp.asarray(width, float)
        self.r0 = jnp.asarray(r0, float)

    def __call__(self, r, type_i, type_j, charge_i, charge_j):
        e = jnp.exp(-_by_type(self.width, type_i, type_j) * (r - _by_type(self.r0, type_i, type_j)))
        return _by_type(self.depth, type_i, type_j) * (e * e - 2 * e)

    def parameter_conditions(self):
        return super().parameter_conditions() + [
            (jnp.all(self.depth >= 0), "`depth` must be ≥ 0."),
            (jnp.all(self.width > 0), "`width` must be > 0."),
        ]
