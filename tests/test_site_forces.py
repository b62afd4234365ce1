"""The closed-form body wrenches of `lievi.SitePotential` (`value_and_body_wrenches`,
used by `lievi.RigidBodies.force`) against the reverse-mode derivative of its energy, and
the all-pairs layout by body offset against a plain double loop over sites."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi._systems._base import AbstractLieSystem

SITES = np.array([[0.0, 0.0, 0.0], [0.25, 0.2, 0.0], [-0.25, 0.2, 0.0]])
CHARGES = np.array([-0.8, 0.4, 0.4])


@functools.cache
def _cached(n, options):
    return _molecules(n, **dict(options))


def _molecules(n, seed=0, **options):
    """`n` three-site molecules (O–O Lennard-Jones, Coulomb between all sites) on a
    jittered line of spacing 1.3, random attitudes: `(system, g)`."""
    rng = np.random.default_rng(seed)
    potential = lievi.SitePotential(
        np.broadcast_to(SITES, (n, 3, 3)),
        (lievi.LennardJones(epsilon=[[1.0, 0.0], [0.0, 0.0]]), lievi.Coulomb()),
        types=np.tile([0, 1, 1], (n, 1)),
        charges=np.tile(CHARGES, (n, 1)),
        **{k: np.asarray(v) if k == "mask" else v for k, v in options.items()},
    )
    system = lievi.RigidBodies(np.tile([0.6, 0.8, 1.0], (n, 1)), np.full(n, 18.0), potential)
    q = rng.normal(size=(n, 4))
    R = jax.vmap(lievi.quaternion_wxyz_to_matrix)(
        jnp.asarray(q / np.linalg.norm(q, axis=1)[:, None])
    )
    centres = np.stack([1.3 * np.arange(n), 0.3 * np.sin(np.arange(n)), np.zeros(n)], 1)
    centres = centres + rng.uniform(-0.1, 0.1, (n, 3))
    g = jnp.broadcast_to(jnp.eye(4), (n, 4, 4)).at[:, :3, :3].set(R).at[:, :3, 3].set(centres)
    return system, g


def _double_loop_energy(system, g):
    """`Σ e(|x_ia − x_jb|)` over sites of different bodies, a loop over bodies `i < j`."""
    potential = system.potential
    x = potential.flat_positions(g).reshape(len(g), -1, 3)
    types, charges = np.asarray(potential.types), np.asarray(potential.charges)
    total = 0.0
    for i in range(len(g)):
        for j in range(i + 1, len(g)):
            r = jnp.linalg.norm(x[i][:, None] - x[j][None], axis=-1)
            args = (types[i][:, None], types[j][None], charges[i][:, None], charges[j][None])
            total = total + sum(jnp.sum(e(r, *args)) for e in potential.pair)
    return total


@pytest.mark.parametrize("n", [1, 2, 5])
def test_all_pairs_by_body_offset_equal_a_double_loop(n):
    # Odd and even numbers of bodies: for even n the bodies n/2 apart are met from both
    # ends and count half each time; one body has no pair.
    system, g = _cached(n, ())
    both = jax.jit(lambda g: (system.potential(g), _double_loop_energy(system, g)))
    assert np.isclose(*both(g), rtol=1e-13, atol=1e-15)


def _all_forms(system, g):
    """`(V, closed-form V, closed-form wrench, reverse-mode force, system.force)`."""
    return jax.jit(
        lambda g: (
            system.potential(g),
            *system.potential.value_and_body_wrenches(g),
            AbstractLieSystem.force(system, g),  # −dV by reverse-mode autodiff
            system.force(g),
        )
    )(g)


@pytest.mark.parametrize(
    "options",
    [
        (),
        (("cutoff", 2.0),),
        (("cutoff", 2.0), ("box", 6.0)),
        (("mask", ((True, True, False),) * 5),),
    ],
    ids=["all-pairs", "cutoff", "box", "mask"],
)
def test_closed_form_wrenches_equal_autodiff(options):
    system, g = _cached(5, options)
    energy, value, wrench, reverse, force = _all_forms(system, g)
    assert np.isclose(value, energy, rtol=1e-14)
    np.testing.assert_allclose(wrench, reverse, rtol=0, atol=1e-12 * np.abs(reverse).max())
    np.testing.assert_array_equal(force, wrench)


def test_closed_form_wrenches_with_a_neighbor_list():
    system, g = _cached(5, (("cutoff", 2.0),))
    pairs = lievi.BruteForceNeighbors(skin=0.4, capacity=96)(system.potential, g)
    listed = lievi.RigidBodies(system.inertia, system.mass, system.potential.with_neighbors(pairs))
    _, _, wrench, reverse, _ = _all_forms(listed, g)
    np.testing.assert_allclose(wrench, reverse, rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrench, _all_forms(system, g)[2], rtol=0, atol=1e-12)


def test_non_finite_energy_gives_a_nan_force():
    system, g = _cached(2, ())
    g = g.at[1, :3, 3].set(g[0, :3, 3])  # two sites coincide
    assert np.all(np.isnan(jax.jit(lambda g: system.force(g))(g)))


def test_all_pairs_force_gathers_whole_bodies_and_scatters_nothing():
    # The force of all pairs reads each body's sites as one block and sends the pulls
    # back by a gather: no per-site index pairs, no scatter-add (a reverse pass through
    # site-by-site gathers scatters; on a small system that was most of a step).
    system, g = _cached(6, ())
    jaxpr = str(jax.make_jaxpr(system.force)(g))
    assert "scatter" not in jaxpr


@pytest.mark.parametrize(
    "energy",
    [
        lievi.LennardJones(epsilon=[[1.0, 0.3], [0.3, 0.5]], sigma=[[1.0, 0.8], [0.8, 0.6]]),
        lievi.Coulomb(k=2.0),
        lievi.Coulomb(softening=0.3),
        lievi.Morse(depth=0.7, width=1.3, r0=1.1),
    ],
    ids=["lennard-jones", "coulomb", "coulomb-softened", "morse"],
)
def test_closed_form_value_and_slope_equal_autodiff(energy):
    # The pair energies' `(e(r), e'(r)/r)` from r² in closed form against the default
    # (√r², then e' by forward-mode autodiff of `e(r)`), per pair and with a scalar r².
    rng = np.random.default_rng(1)
    r2 = jnp.asarray(rng.uniform(0.4, 6.0, 50))
    args = (
        jnp.asarray(rng.integers(0, 2, 50)),
        jnp.asarray(rng.integers(0, 2, 50)),
        jnp.asarray(rng.normal(size=50)),
        jnp.asarray(rng.normal(size=50)),
    )
    default = lievi.AbstractPairEnergy.value_and_slope
    for squared in (r2, r2[3]):
        for closed, expected in zip(
            energy.value_and_slope(squared, *args), default(energy, squared, *args)
        ):
            assert closed.shape == expected.shape
            assert np.allclose(closed, expected, rtol=1e-13, atol=1e-15)


def test_mutual_gravity_closed_form_wrenches_equal_autodiff():
    # Three bodies, one of them padded with a point of mass 0 (in no pair), random poses.
    rng = np.random.default_rng(4)
    masses = [np.array([1.0, 0.6, 0.8]), np.array([0.5, 0.4]), np.array([0.7, 0.2, 0.3])]
    points = [rng.uniform(-0.2, 0.2, (len(m), 3)) for m in masses]
    system = lievi.gravitating_bodies(1.3, masses, points, extra_inertia=0.01 * np.eye(3)[None])
    q = rng.normal(size=(3, 4))
    R = jax.vmap(lievi.quaternion_wxyz_to_matrix)(
        jnp.asarray(q / np.linalg.norm(q, axis=1)[:, None])
    )
    centres = np.array([[0.0, 0.0, 0.0], [1.1, 0.4, -0.2], [-0.3, 1.2, 0.5]])
    g = jnp.broadcast_to(jnp.eye(4), (3, 4, 4)).at[:, :3, :3].set(R).at[:, :3, 3].set(centres)
    energy, value, wrench, reverse, force = _all_forms(system, g)
    assert np.isclose(value, energy, rtol=1e-14)
    np.testing.assert_allclose(wrench, reverse, rtol=0, atol=1e-13 * np.abs(reverse).max())
    np.testing.assert_array_equal(force, wrench)
