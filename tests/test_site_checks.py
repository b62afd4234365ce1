"""The parameter checks of site potentials, springs, pair lists, pair tables and the
inertias of several bodies hold alike eagerly (a `ValueError` naming the argument) and
traced (`RESULTS.invalid_input` from a run under `jax.jit`/`jax.vmap`): each is written
once, as a condition (`parameter_conditions`).

The traced cases share one compiled program: two bodies of one site each, coupled by a
site potential with every option (type tables, cut-off, box, pair list) and a spring,
each case one parameter away from an admissible scene; two steps of
`LiePoissonSplitting`. Float64.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi._checks import all_hold
from lievi._systems._se3_potentials import point_mass_body

SUCCESS, INVALID = int(lievi.RESULTS.successful), int(lievi.RESULTS.invalid_input)
SITES = jnp.zeros((2, 1, 3))  # one site at each body's centre
G0 = jnp.stack([jnp.eye(4), jnp.eye(4).at[0, 3].set(1.0)])  # the sites 1 apart
M0 = jnp.array([[0.1, -0.2, 0.3, 0.0, 0.1, 0.0], [0.0, 0.2, -0.1, 0.1, 0.0, 0.0]])
LJ = lievi.LennardJones(1.0, 0.9)
FILL = 2  # the padding index of a pair list of two sites
TABLE = np.array([[1.0, 0.8], [0.8, 0.9]])  # a symmetric table over two site types

AXIS = np.array([0.7, 0.3, 0.2])  # a dumbbell along it: rounding leaves moments of ±1e-16
DUMBBELLS = np.array([[AXIS, -AXIS], [AXIS + [3.0, 0, 0], -AXIS + [3.0, 0, 0]]])
SINGULAR = np.asarray(jax.vmap(point_mass_body)(jnp.ones((2, 2)), jnp.asarray(DUMBBELLS))[2])


# ---- eagerly: a ValueError naming the argument ---------------------------------------------


@pytest.mark.parametrize(
    "cutoff, box, match",
    [(3.0, 4.0, "`cutoff`"), (-1.0, 4.0, "`cutoff`"), (1.0, -4.0, "`box`")],
)
def test_cutoff_and_box(cutoff, box, match):
    """A cut-off more than half the box, or not positive; a box side not positive."""
    with pytest.raises(ValueError, match=match):
        lievi.SitePotential(SITES, LJ, cutoff=cutoff, box=box)


@pytest.mark.parametrize(
    "types, match", [([[0], [5]], "table over 2 site types"), ([[0], [-1]], "≥ 0")]
)
def test_site_types_within_the_tables(types, match):
    with pytest.raises(ValueError, match=match):
        lievi.SitePotential(SITES, lievi.LennardJones(TABLE, 0.9), types=types)


@pytest.mark.parametrize(
    "row, match",
    [
        ((0, 0, 7, 0), "outside"),
        ((0, 3, 1, 0), "outside"),
        ((-1, 0, 1, 0), "outside"),
        ((0, 0, 0, 0), "one body"),
    ],
)
def test_spring_pairs(row, match):
    """A spring naming body 7 of 2, site 3 of 1, a negative index, or joining one body."""
    with pytest.raises(ValueError, match=f"`pairs` row 0 .*{match}"):
        lievi.SiteSprings(SITES, [row], 1.0, 0.5)


def listed(pairs):
    return lievi.SitePotential(SITES, LJ, cutoff=1.4, neighbors=pairs)


def test_padding_in_either_column_is_no_pair():
    """A row with the padding index in its first column is padding, as one with it in the
    second: the energy of the list is that of its one real pair."""
    one_pair = listed([[0, 1], [FILL, FILL]])(G0)
    assert float(one_pair) < -0.1  # the pair is within the cut-off and counts
    for pairs in ([[0, 1], [FILL, 0]], [[FILL, 1], [0, 1]], [[FILL, FILL], [FILL, 1]]):
        expected = one_pair if [0, 1] in pairs else 0.0
        np.testing.assert_allclose(listed(pairs)(G0), expected, rtol=1e-15, atol=0)


@pytest.mark.parametrize(
    "pairs", [[[0, 1], [0, 1]], [[0, 1], [1, 0]]], ids=["repeated", "both-ways"]
)
def test_duplicate_pairs(pairs):
    """A pair listed twice, or both ways round, is refused (it would count twice); a
    single pair listed `(j, i)` is the pair `(i, j)`."""
    with pytest.raises(ValueError, match=r"`neighbors` lists a pair twice \(row 1\)"):
        listed(pairs)
    np.testing.assert_allclose(
        listed([[1, 0], [FILL, FILL]])(G0), listed([[0, 1], [FILL, FILL]])(G0), rtol=1e-15
    )


def test_a_builders_list_skips_only_the_repeat_check():
    """A builder's list inside a run's program (`SitePotential.from_builder`) is not
    sorted to look for repeated pairs (a builder lists each pair once): that condition
    alone is left out; an index outside the sites still fails, traced. A list given by
    hand keeps every check."""
    potential = lievi.SitePotential(SITES, LJ, cutoff=2.0)
    repeated, outside = jnp.array([[0, 1], [0, 1]]), jnp.array([[0, 1], [0, 3]])
    assert bool(all_hold(potential.from_builder(repeated).parameter_conditions()))
    assert not bool(all_hold(potential.from_builder(outside).parameter_conditions()))
    with pytest.raises(ValueError, match="lists a pair twice"):
        potential.with_neighbors(repeated)
    assert not potential.with_neighbors(jnp.array([[0, 1], [FILL, FILL]])).built


@pytest.mark.parametrize("name", ["epsilon", "sigma"])
def test_asymmetric_table(name):
    """The energy of a pair must not depend on which of its sites is listed first."""
    with pytest.raises(ValueError, match=f"`{name}` must be symmetric"):
        lievi.LennardJones(**{name: TABLE + np.array([[0.0, 0.0], [0.1, 0.0]])})


def test_singular_inertia_points_to_extra_inertia():
    """Two dumbbells of point masses have no moment about their axes: refused where the
    system is built, naming `extra_inertia`, not later as a step too large."""
    with pytest.raises(ValueError, match=r"`inertia` is singular \(body 0\).*extra_inertia"):
        lievi.gravitating_bodies(1.0, np.ones((2, 2)), DUMBBELLS)
    with pytest.raises(ValueError, match="extra_inertia"):
        lievi.full_body_problem(1.0, np.ones(2), DUMBBELLS[0])
    with pytest.raises(ValueError, match="extra_inertia"):
        lievi.RigidRotors(SINGULAR)
    extra = np.broadcast_to(1e-3 * np.eye(3), (2, 3, 3))
    lievi.gravitating_bodies(1.0, np.ones((2, 2)), DUMBBELLS, extra_inertia=extra)


# ---- traced: RESULTS.invalid_input --------------------------------------------------------


class Scene(lievi.AbstractPotential):
    """Pairs and springs summed, with the conditions of both (a compound potential)."""

    sites: lievi.SitePotential
    springs: lievi.SiteSprings

    def parameter_conditions(self):
        return self.sites.parameter_conditions() + self.springs.parameter_conditions()

    def __call__(self, g):
        return self.sites(g) + self.springs(g)


GOOD = dict(
    inertia=np.broadcast_to(np.eye(3), (2, 3, 3)),
    cutoff=1.4,
    box=4.0,
    types=np.array([[0], [1]]),
    epsilon=TABLE,
    sigma=TABLE,
    neighbors=np.array([[0, 1], [FILL, FILL]]),
    springs=np.array([[0, 0, 1, 0]]),
)
CASES = {  # one parameter changed -> the expected result
    "admissible": ({}, SUCCESS),
    "padding-first": (dict(neighbors=[[FILL, 0], [0, 1]]), SUCCESS),
    "cutoff>L/2": (dict(cutoff=3.0), INVALID),
    "cutoff<0": (dict(cutoff=-1.0), INVALID),
    "box<0": (dict(box=-4.0), INVALID),
    "type-5-of-2": (dict(types=[[0], [5]]), INVALID),
    "type-negative": (dict(types=[[0], [-1]]), INVALID),
    "spring-body-7": (dict(springs=[[0, 0, 7, 0]]), INVALID),
    "spring-site-3": (dict(springs=[[0, 3, 1, 0]]), INVALID),
    "spring-one-body": (dict(springs=[[0, 0, 0, 0]]), INVALID),
    "pair-repeated": (dict(neighbors=[[0, 1], [0, 1]]), INVALID),
    "pair-both-ways": (dict(neighbors=[[0, 1], [1, 0]]), INVALID),
    "epsilon-asymmetric": (dict(epsilon=[[1.0, 0.8], [0.7, 0.9]]), INVALID),
    "sigma-asymmetric": (dict(sigma=[[1.0, 0.8], [0.7, 0.9]]), INVALID),
    "inertia-singular": (dict(inertia=SINGULAR), INVALID),
}


def run(inertia, cutoff, box, types, epsilon, sigma, neighbors, springs):
    pair = lievi.LennardJones(epsilon, sigma)
    sites = lievi.SitePotential(SITES, pair, types, cutoff=cutoff, box=box, neighbors=neighbors)
    scene = Scene(sites, lievi.SiteSprings(SITES, springs, 1.0, 0.5))
    system = lievi.RigidBodies(inertia, jnp.ones(2), scene)
    method = lievi.LiePoissonSplitting()
    return lievi.simulate(system, method, G0, M0, h=0.01, n_steps=2, throw=False).result


def test_bad_parameters_traced():
    """Every case above as one program under `jax.jit(jax.vmap(…))`: the admissible
    scenes run, each bad parameter gives `invalid_input` (never a clamped index, never a
    silent number)."""
    stacked = {
        name: jnp.stack([jnp.asarray(changes.get(name, value)) for changes, _ in CASES.values()])
        for name, value in GOOD.items()
    }
    got = jax.jit(jax.vmap(run))(**stacked)
    assert dict(zip(CASES, map(int, got))) == {name: code for name, (_, code) in CASES.items()}


# ---- bodies of different numbers of points -----------------------------------------------


def test_gravity_of_bodies_of_different_sizes():
    """A binary of a 3-point body and a 1-point body given as lists: padded with points of
    mass 0, it is the binary whose second body is its point split into 3 coincident
    points of a third of the mass (the same gravity, inertia and mass), to round-off, in
    its energy and a 3-step run."""
    big = np.array([[0.4, 0.0, 0.0], [-0.3, 0.2, 0.0], [0.0, -0.1, 0.3]])
    masses = [np.array([1.0, 2.0, 1.5]), np.array([0.9])]
    points = [big, np.array([[5.0, 1.0, 0.0]])]
    extra = np.broadcast_to(0.1 * np.eye(3), (2, 3, 3))
    ragged = lievi.gravitating_bodies(1.0, masses, points, extra_inertia=extra)
    split = lievi.gravitating_bodies(
        1.0,
        np.array([masses[0], [0.3, 0.3, 0.3]]),
        np.array([big, [[5.0, 1.0, 0.0]] * 3]),
        extra_inertia=extra,
    )
    np.testing.assert_array_equal(ragged.potential.masses[1], [0.9, 0.0, 0.0])
    np.testing.assert_allclose(ragged.inertia, split.inertia, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(ragged.mass, split.mass, rtol=1e-15)
    g0 = jnp.stack([jnp.eye(4), jnp.eye(4).at[:3, 3].set(jnp.array([5.0, 1.0, 0.0]))])
    np.testing.assert_allclose(ragged.potential(g0), split.potential(g0), rtol=1e-14)
    runs = [
        lievi.simulate(s, lievi.LiePoissonSplitting(), g0, M0, h=0.05, n_steps=3)
        for s in (ragged, split)
    ]
    np.testing.assert_allclose(runs[0].m, runs[1].m, rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match="≥ 0"):
        lievi.MutualGravity(1.0, [[1.0, -1.0], [1.0, 1.0]], np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="each body a point of mass > 0"):
        lievi.MutualGravity(1.0, [[1.0, 1.0], [0.0, 0.0]], np.zeros((2, 2, 3)))


def test_sites_of_bodies_of_different_sizes():
    """A two-site body and a one-site body given as lists: the energy is the sum over the
    real pairs (written out here), and its force is finite where the padding site (at
    the second body's centre) coincides with a site of the first body."""
    pair = (lievi.LennardJones(TABLE, 0.9), lievi.Coulomb())
    sites = [np.array([[0.5, 0.0, 0.0], [-0.4, 0.1, 0.0]]), np.array([[0.0, 0.6, 0.0]])]
    types, charges = [[0, 1], [1]], [[0.3, -0.2], [0.5]]
    potential = lievi.SitePotential(sites, pair, types, charges)
    np.testing.assert_array_equal(potential.mask, [[True, True], [True, False]])
    # The second body's centre on the first's site 0: its padding site lies there.
    g = jnp.stack([jnp.eye(4), jnp.eye(4).at[0, 3].set(0.5)])
    second = np.array([0.5, 0.6, 0.0])
    expected = 0.0
    for x, t, q in zip(sites[0], types[0], charges[0]):
        r = np.linalg.norm(x - second)
        s6 = (0.9 / r) ** 6
        expected += 4 * TABLE[t, 1] * (s6 * s6 - s6) + q * 0.5 / r
    np.testing.assert_allclose(potential(g), expected, rtol=1e-14)
    system = lievi.RigidBodies(jnp.ones((2, 3)), jnp.ones(2), potential)
    assert bool(jnp.all(jnp.isfinite(system.force(g))))
    # With a cut-off, over a neighbour list (which lists the padding site's pairs too).
    cut = lievi.SitePotential(sites, pair, types, charges, cutoff=2.0)
    pairs = lievi.BruteForceNeighbors(0.5)(cut, g)
    np.testing.assert_allclose(cut.with_neighbors(pairs)(g), cut(g), rtol=1e-14)
    assert float(cut(g)) != 0.0
