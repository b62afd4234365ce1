"""Periodic boxes, cut-offs and neighbour lists of `lievi.SitePotential`.

Decided by checks that do not use the code under test's own minimum image or pair list:
the periodic energy against an explicit sum over the box's images (NumPy, the
shifted-force Lennard-Jones written out); the neighbour-list energy and forces against
the all-pairs cut-off potential; the brute-force builder against jax-md's cell list; a
segmented run with rebuilds against one run on the all-pairs cut-off potential; the total
linear momentum in a periodic box. Float64. The runs use `LiePoissonSplitting` (the
quickest coupled program to compile) and share one pair-list capacity, so that the
segments of every run reuse one compiled step.
"""

import importlib.util
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi import diagnostics as dg

SIGMA, EPSILON, CUTOFF, BOX, SKIN = 0.8, 1.0, 1.4, 3.0, 0.3
CAPACITY = 400  # one shape for every list below: one compile of the listed step
H, METHOD = 0.005, lievi.LiePoissonSplitting()


def _poses(rng, positions):
    rotations = [lievi.SO3.exp(jnp.asarray(rng.normal(size=3))) for _ in positions]
    return jnp.stack(
        [
            lievi.SE3.from_rotation_translation(R, jnp.asarray(p))
            for R, p in zip(rotations, positions)
        ]
    )


def box_problem(box=BOX, cutoff=CUTOFF, seed=0):
    """Eight two-site bodies on a jittered 2×2×2 lattice filling a periodic box, random
    orientations and momenta (total linear momentum not zero)."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    positions = grid * box / 2 + 0.3 + rng.uniform(-0.1, 0.1, size=(8, 3))
    sites = np.zeros((8, 2, 3))
    sites[:, 0, 0], sites[:, 1, 0] = 0.2, -0.2
    potential = lievi.SitePotential(
        sites, lievi.LennardJones(EPSILON, SIGMA), cutoff=cutoff, box=box
    )
    system = lievi.RigidBodies(jnp.asarray(rng.uniform(0.5, 1.5, (8, 3))), jnp.ones(8), potential)
    return system, _poses(rng, positions), jnp.asarray(rng.normal(size=(8, 6)) * 0.5)


def _lj_shifted_force(r):
    s6 = (SIGMA / r) ** 6
    e = 4 * EPSILON * (s6 * s6 - s6)
    sc6 = (SIGMA / CUTOFF) ** 6
    e_c = 4 * EPSILON * (sc6 * sc6 - sc6)
    slope_c = 4 * EPSILON * (-12 * sc6 * sc6 + 6 * sc6) / CUTOFF
    return e - e_c - (r - CUTOFF) * slope_c


def _sum_over_images(x, k, box):
    """Σ over pairs of sites on different bodies and over the images `x_j + n L`,
    `n ∈ {−2, …, 2}³`, of the shifted-force energy within the cut-off."""
    shifts = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    total = 0.0
    for a in range(len(x)):
        for b in range(a + 1, len(x)):
            if a // k == b // k:
                continue
            r = np.linalg.norm(x[a] - x[b] + shifts * box, axis=1)
            total += np.sum(_lj_shifted_force(r[r < CUTOFF]))
    return total


def test_minimum_image():
    d = jnp.asarray(np.random.default_rng(0).uniform(-10, 10, size=(100, 3)))
    box = jnp.array([2.0, 3.0, 5.0])
    image = lievi.minimum_image(d, box)
    assert jnp.all(jnp.abs(image) <= box / 2 + 1e-15)
    whole = (d - image) / box
    assert jnp.max(jnp.abs(whole - jnp.round(whole))) < 1e-13


def test_periodic_energy_is_the_sum_over_images():
    """Against an explicit sum over 5³ images: relative 1e-12. Moving a body by a box
    side (positions are not wrapped) changes nothing."""
    system, g0, _ = box_problem()
    potential = jax.jit(lambda g: system.potential(g))
    x = np.asarray(system.potential.flat_positions(g0))
    expected = _sum_over_images(x, 2, BOX)
    assert abs(float(potential(g0)) - expected) <= 1e-12 * abs(expected)
    moved = g0.at[3, :3, 3].add(jnp.array([BOX, -2 * BOX, 0.0]))
    assert abs(float(potential(moved)) - expected) <= 1e-12 * abs(expected)


@pytest.mark.parametrize("box", [BOX, None], ids=["periodic", "free"])
def test_neighbor_list_equals_all_pairs(box):
    """Energy and gradient (all pose entries) of the listed potential equal the all-pairs
    cut-off potential's to 1e-12 relative, at the build and after every site moved less
    than skin/2."""
    system, g0, _ = box_problem()
    potential = lievi.SitePotential(
        system.potential.sites, system.potential.pair, cutoff=CUTOFF, box=box
    )
    pairs = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)(potential, g0)
    listed = potential.with_neighbors(pairs)
    rng = np.random.default_rng(5)
    both = jax.jit(lambda g: (jax.value_and_grad(potential)(g), jax.value_and_grad(listed)(g)))
    for g in (g0, g0.at[:, :3, 3].add(jnp.asarray(rng.uniform(-0.06, 0.06, (8, 3))))):
        (e_all, grad_all), (e_list, grad_list) = both(g)
        assert abs(e_list - e_all) <= 1e-12 * abs(e_all)
        assert jnp.max(jnp.abs(grad_list - grad_all)) <= 1e-12 * jnp.max(jnp.abs(grad_all))


@pytest.mark.parametrize("box", [BOX, None], ids=["periodic", "free"])
def test_brute_force_list_equals_a_double_loop(box, monkeypatch):
    """The builder's pairs are exactly those of a plain double loop over all sites (the
    minimum image by `round`, as `minimum_image`), in row-major order, padded with the
    fill index; with blocks of 3 rows (`_BLOCK_PAIRS`), so that a block boundary and a
    padded last block are exercised."""
    from lievi._systems import _neighbors

    system, g0, _ = box_problem()
    potential = lievi.SitePotential(
        system.potential.sites, system.potential.pair, cutoff=CUTOFF, box=box
    )
    x = np.asarray(potential.flat_positions(g0))
    n, radius = len(x), CUTOFF + SKIN
    expected = []
    for i in range(n):
        for j in range(i + 1, n):
            d = x[i] - x[j]
            if box is not None:
                d = d - box * np.round(d / box)
            if i // 2 != j // 2 and d @ d < radius * radius:
                expected.append((i, j))
    monkeypatch.setattr(_neighbors, "_BLOCK_PAIRS", 3 * n)
    jax.clear_caches()  # `_near_pairs` reads the block size when traced
    pairs = np.asarray(lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)(potential, g0))
    assert 0 < len(expected) < CAPACITY and n % 3 != 0
    assert [tuple(p) for p in pairs[: len(expected)]] == expected
    assert np.all(pairs[len(expected) :] == n)


def test_energy_vanishes_smoothly_at_the_cutoff():
    """Energy and force of a pair go to zero at r_c: continuous, so the integrator's
    energy error is not kicked when a pair crosses it."""
    sites = jnp.zeros((2, 1, 3))
    potential = lievi.SitePotential(sites, lievi.LennardJones(EPSILON, SIGMA), cutoff=CUTOFF)

    @jax.jit
    def energy(r):
        g = jnp.broadcast_to(jnp.eye(4), (2, 4, 4)).at[1, 0, 3].set(r)
        return potential(g)

    for r in (CUTOFF - 1e-7, CUTOFF + 1e-7):
        assert abs(energy(r)) < 1e-12 and abs(jax.grad(energy)(r)) < 1e-6
    assert energy(CUTOFF + 0.5) == 0.0
    assert abs(energy(1.0) - _lj_shifted_force(1.0)) < 1e-14


def test_shift_per_pair_with_tables_and_charges():
    """Type tables and charges: the shift is taken pair by pair; each pair's energy is 0
    beyond r_c and continuous at it. Against the pair energies called directly."""
    sites = jnp.zeros((2, 1, 3))
    lj = lievi.LennardJones(
        jnp.array([[1.0, 0.5], [0.5, 2.0]]), jnp.array([[0.8, 0.9], [0.9, 1.0]])
    )
    pair = (lj, lievi.Coulomb())
    potential = lievi.SitePotential(
        sites, pair, types=[[0], [1]], charges=[[0.5], [-0.3]], cutoff=CUTOFF
    )

    @jax.jit
    def energy(r):
        return potential(jnp.broadcast_to(jnp.eye(4), (2, 4, 4)).at[1, 2, 3].set(r))

    def direct(r):
        args = (jnp.array([0]), jnp.array([1]), jnp.array([0.5]), jnp.array([-0.3]))
        return sum(e(jnp.array([r]), *args)[0] for e in pair)

    slope = jax.grad(direct)(CUTOFF)
    expected = direct(1.0) - direct(CUTOFF) - (1.0 - CUTOFF) * slope
    assert abs(energy(1.0) - expected) < 1e-13
    assert abs(energy(CUTOFF - 1e-7)) < 1e-12 and energy(CUTOFF + 1e-7) == 0.0


@pytest.mark.parametrize("box", [6.0, None], ids=["periodic", "free"])
def test_brute_force_and_jax_md_lists_agree(box):
    pytest.importorskip("jax_md")
    rng = np.random.default_rng(3)
    n = 60
    sites = jnp.asarray(rng.normal(size=(n, 3, 3)) * 0.3)
    potential = lievi.SitePotential(sites, lievi.LennardJones(), cutoff=1.5, box=box)
    g = _poses(rng, rng.uniform(0, 6.0, size=(n, 3)) + (0 if box is None else 6.0 * 3))
    brute = np.asarray(lievi.BruteForceNeighbors(0.3)(potential, g))
    cells = np.asarray(lievi.JaxMDNeighbors(0.3)(potential, g))
    assert brute.shape == cells.shape
    assert np.all(np.unique(brute, axis=0) == np.unique(cells, axis=0))  # the same set
    real = brute[brute[:, 1] < 3 * n]
    assert len(real) > 100 and np.all(real[:, 0] // 3 != real[:, 1] // 3)


def test_jax_md_rebuilds_agree_with_brute_force():
    """jax-md's incremental rebuild (`update`) after the sites moved, and in free space
    its reallocation when a site left the bounding box: the brute-force pair set."""
    pytest.importorskip("jax_md")
    rng = np.random.default_rng(4)
    n = 40
    sites = jnp.asarray(rng.normal(size=(n, 2, 3)) * 0.3)
    g = _poses(rng, rng.uniform(0, 5.0, size=(n, 3)))
    for box in (None, 5.0):
        potential = lievi.SitePotential(sites, lievi.LennardJones(), cutoff=1.2, box=box)
        cells = lievi.JaxMDNeighbors(0.3, capacity=CAPACITY)
        brute = lievi.BruteForceNeighbors(0.3, capacity=CAPACITY)
        _, state = cells.build(potential, g)
        moved = g.at[:, :3, 3].add(jnp.asarray(rng.uniform(-0.5, 0.5, (n, 3))))
        far = moved.at[0, :3, 3].add(jnp.array([20.0, 0.0, 0.0]))
        for poses in (moved, far):
            pairs, state = cells.build(potential, poses, state)
            expected = np.unique(np.asarray(brute(potential, poses)), axis=0)
            assert np.all(np.unique(np.asarray(pairs), axis=0) == expected)


def test_jax_md_later_runs_update_the_allocated_list(monkeypatch):
    """jax-md allocates its list on the host (seconds for 10⁴ sites): a later run's first
    build in the same box (`state=None`, as each `simulate_with_neighbor_list` call
    starts) updates the list allocated before, with the same pairs, and at the very
    positions of the last build keeps it (no update). (The box, cut-off and skin of
    `test_jax_md_rebuilds_agree_with_brute_force`: one compiled `update`.)"""
    pytest.importorskip("jax_md")
    from lievi._systems import _neighbors

    allocations, updates = [], []

    def counted(*key):
        allocate, update, allocated = original(*key)
        return (
            lambda x: allocations.append(len(x)) or allocate(x),
            lambda x, neighbors: updates.append(len(x)) or update(x, neighbors),
            allocated,
        )

    original = _neighbors._jax_md_list
    monkeypatch.setattr(_neighbors, "_jax_md_list", counted)
    rng = np.random.default_rng(5)
    n = 40
    sites = jnp.asarray(rng.normal(size=(n, 2, 3)) * 0.3)
    potential = lievi.SitePotential(sites, lievi.LennardJones(), cutoff=1.2, box=5.0)
    g = _poses(rng, rng.uniform(0, 5.0, size=(n, 3)))
    cells = lievi.JaxMDNeighbors(0.3, capacity=CAPACITY)
    first, _ = cells.build(potential, g)
    before = len(updates)
    again, _ = cells.build(potential, g)
    assert len(allocations) <= 1  # none if an earlier test allocated this box's list
    assert np.all(np.asarray(first) == np.asarray(again))
    # The second build, at the first's positions, kept its list; elsewhere each first
    # build updates it: the brute-force pairs at the moved poses, the first list back at g.
    assert len(updates) == before
    moved = g.at[:, :3, 3].add(jnp.asarray(rng.uniform(-0.5, 0.5, (n, 3))))
    there, _ = cells.build(potential, moved)
    back, _ = cells.build(potential, g)
    assert len(updates) == before + 2 and len(allocations) <= 1
    brute = lievi.BruteForceNeighbors(0.3, capacity=CAPACITY)(potential, moved)
    assert np.array_equal(np.unique(np.asarray(there), axis=0), np.unique(brute, axis=0))
    assert np.all(np.asarray(back) == np.asarray(first))


def test_jax_md_in_a_small_box_warns_nothing(recwarn):
    """A periodic box of fewer than three list radii per side (`box_problem`: 3 against
    3 × 1.7), where jax-md has no cell list and tests every pair, in float64: no JAX
    `FutureWarning` (jax-md scatters int64 indices into its int32 list there, which later
    JAX releases make an error), on the first build and on a rebuild, and the brute-force
    pair set."""
    pytest.importorskip("jax_md")
    system, g0, _ = box_problem()
    cells = lievi.JaxMDNeighbors(SKIN, capacity=CAPACITY)
    brute = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)
    pairs, state = cells.build(system.potential, g0)
    moved = g0.at[:, :3, 3].add(0.1)
    again, _ = cells.build(system.potential, moved, state)
    future = [str(w.message) for w in recwarn if issubclass(w.category, FutureWarning)]
    assert not future, future
    for poses, found in ((g0, pairs), (moved, again)):
        expected = np.unique(np.asarray(brute(system.potential, poses)), axis=0)
        assert len(expected) > 10
        assert np.array_equal(np.unique(np.asarray(found), axis=0), expected)


def test_device_rebuilds_agree_with_host_builds():
    """`rebuild` (traceable, run inside the compiled program), from a first `build`'s
    state: the pair set of a build on the host at the moved poses — for the brute-force
    builder, and for jax-md's in a periodic box (its `update`) and in free space where a
    site has left the first allocation's bounding box (every pair tested instead). A
    capacity too small is reported as an overflow. (The box, cut-off and skin of
    `test_jax_md_rebuilds_agree_with_brute_force`, whose jax-md lists this reuses.)"""
    rng = np.random.default_rng(4)
    n = 40
    sites = jnp.asarray(rng.normal(size=(n, 2, 3)) * 0.3)
    g = _poses(rng, rng.uniform(0, 5.0, size=(n, 3)))
    moved = g.at[:, :3, 3].add(jnp.asarray(rng.uniform(-0.5, 0.5, (n, 3))))
    far = moved.at[0, :3, 3].add(jnp.array([20.0, 0.0, 0.0]))
    cases = [(lievi.BruteForceNeighbors, None, moved), (lievi.BruteForceNeighbors, 5.0, moved)]
    if importlib.util.find_spec("jax_md"):
        cases += [(lievi.JaxMDNeighbors, 5.0, moved), (lievi.JaxMDNeighbors, None, far)]
    for kind, box, poses in cases:
        potential = lievi.SitePotential(sites, lievi.LennardJones(), cutoff=1.2, box=box)
        builder = kind(0.3, capacity=CAPACITY)
        _, state = builder.build(potential, g)
        # Eagerly: the operations the program traces, without a program per case.
        pairs, _, overflow = builder.rebuild(potential, poses, state)
        brute = lievi.BruteForceNeighbors(0.3, capacity=CAPACITY)
        expected = np.unique(np.asarray(brute(potential, poses)), axis=0)
        assert not bool(overflow) and len(expected) > 10
        assert np.array_equal(np.unique(np.asarray(pairs), axis=0), expected)
        small = lievi.BruteForceNeighbors(0.3, capacity=10)
        assert bool(small.rebuild(potential, poses, None)[2])


@pytest.fixture(scope="module")
def segmented():
    system, g0, m0 = box_problem()
    builder = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)
    sol = lievi.simulate_with_neighbor_list(
        system,
        METHOD,
        g0,
        m0,
        h=H,
        n_steps=200,
        rebuild_every=10,
        save=lievi.Save(every=10),
        builder=builder,
    )
    return system, g0, m0, sol


def test_run_is_one_program(segmented, monkeypatch):
    """With a builder that rebuilds on the device, the run is one compiled program: its
    one build on the host is the first (the 19 others inside the program, as jax-md's
    users rebuild inside their loop), no segment is called from the host, and the saves
    are those of the fixture's run (the same program, not compiled again)."""
    from lievi import _simulate_neighbors
    from lievi._systems import _neighbors

    system, g0, m0, sol = segmented
    host_builds, segments = [], []
    build, simulate = _neighbors._all_pairs_list, _simulate_neighbors.simulate
    monkeypatch.setattr(
        _neighbors, "_all_pairs_list", lambda *a: host_builds.append(1) or build(*a)
    )
    monkeypatch.setattr(
        _simulate_neighbors, "simulate", lambda *a, **k: segments.append(1) or simulate(*a, **k)
    )
    again = lievi.simulate_with_neighbor_list(
        system,
        METHOD,
        g0,
        m0,
        h=H,
        n_steps=200,
        rebuild_every=10,
        save=lievi.Save(every=10),
        builder=lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY),
    )
    assert len(host_builds) == 1 and not segments
    assert int(again.stats["neighbor_builds"]) == 20
    assert jnp.array_equal(again.g, sol.g) and jnp.array_equal(again.m, sol.m)


@pytest.mark.extended  # 10 s
def test_segmented_run_equals_all_pairs_run(segmented):
    """200 steps, a rebuild every 10: the saves equal one `simulate` on the all-pairs
    cut-off potential to 1e-12 (absolute; the state is of order 1)."""
    system, g0, m0, sol = segmented
    reference = lievi.simulate(system, METHOD, g0, m0, h=H, n_steps=200, save=lievi.Save(every=10))
    assert sol.g.shape == reference.g.shape and jnp.all(sol.ts == reference.ts)
    assert jnp.max(jnp.abs(sol.g - reference.g)) < 1e-12
    assert jnp.max(jnp.abs(sol.m - reference.m)) < 1e-12
    assert int(sol.stats["neighbor_builds"]) == 20 and int(sol.result) == 0
    assert int(sol.stats["neighbor_reruns"]) == 0
    assert 0 < float(sol.stats["neighbor_max_displacement"]) < SKIN / 2
    assert int(sol.stats["total_newton_iterations"]) == int(
        reference.stats["total_newton_iterations"]
    )
    # Some body crossed a wall of the box (unwrapped positions).
    assert jnp.any(jnp.abs(sol.g[:, :, :3, 3]) > BOX) or jnp.any(sol.g[:, :, :3, 3] < 0)


@pytest.mark.parametrize("rebuild_after", [0.25, 0.5])
def test_reused_lists_equal_all_pairs_run(segmented, rebuild_after):
    """`rebuild_after`: a list is kept across segments until a site has moved that
    fraction of the skin, and a segment in which it went stale is run again with a fresh
    list. Segments of 2 steps over 200: fewer builds than segments, reruns at 1/2 (a list
    is kept until it fails) and none at 1/4 here, and the same saves as the all-pairs run
    to 1e-12 (absolute; the state is of order 1)."""
    system, g0, m0, _ = segmented
    builder = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)
    sol = lievi.simulate_with_neighbor_list(
        system,
        METHOD,
        g0,
        m0,
        h=H,
        n_steps=200,
        rebuild_every=2,
        save=lievi.Save(every=10),
        builder=builder,
        rebuild_after=rebuild_after,
    )
    reference = lievi.simulate(system, METHOD, g0, m0, h=H, n_steps=200, save=lievi.Save(every=10))
    builds, reruns = int(sol.stats["neighbor_builds"]), int(sol.stats["neighbor_reruns"])
    assert int(sol.result) == 0 and builds < 50
    assert (reruns >= 1) if rebuild_after == 0.5 else (reruns == 0)
    assert 0 < float(sol.stats["neighbor_max_displacement"]) < SKIN / 2
    assert jnp.max(jnp.abs(sol.g - reference.g)) < 1e-12
    assert jnp.max(jnp.abs(sol.m - reference.m)) < 1e-12


@pytest.mark.extended  # 20 s
def test_segmented_run_with_forcing(segmented):
    """A control per body over the whole run (each segment reads its own rows) plus a
    time-dependent damping law (each segment starts at its own time): the saves equal
    one forced `simulate` on the all-pairs cut-off potential to 1e-12. The control is
    not constant in time, so a segment that read the first rows again would differ."""
    system, g0, m0, _ = segmented
    n_steps = 40
    u = 0.05 * jnp.sin(jnp.arange(n_steps)[:, None, None] * 0.3 + jnp.arange(6.0))
    u = jnp.broadcast_to(u, (n_steps, 8, 6))
    damping = lievi.ForceLaw(lambda t, g, m, c: -c * (1 + t) * m)
    forcing = (lievi.Control(u), damping)
    builder = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)
    kwargs = dict(h=H, n_steps=n_steps, save=lievi.Save(every=10), forcing=forcing, args=0.1)
    sol = lievi.simulate_with_neighbor_list(
        system, METHOD, g0, m0, rebuild_every=10, builder=builder, **kwargs
    )
    reference = lievi.simulate(system, METHOD, g0, m0, **kwargs)
    unforced = lievi.simulate(
        system, METHOD, g0, m0, h=H, n_steps=n_steps, save=lievi.Save(every=10)
    )
    assert int(sol.result) == 0 and int(sol.stats["neighbor_builds"]) == 4
    assert jnp.max(jnp.abs(sol.g - reference.g)) < 1e-12
    assert jnp.max(jnp.abs(sol.m - reference.m)) < 1e-12
    assert jnp.max(jnp.abs(sol.m - unforced.m)) > 1e-3  # the forcing acts
    with pytest.raises(ValueError, match="forcing"):
        lievi.simulate_with_neighbor_list(
            system,
            METHOD,
            g0,
            m0,
            h=H,
            n_steps=n_steps,
            rebuild_every=10,
            builder=builder,
            forcing=lievi.Control(u[:-1]),
        )


@pytest.mark.extended  # 11 s
def test_batch_of_systems_with_their_own_lists():
    """`simulate_batch` over boxes that each carry their own list (built at each one's
    initial poses, one capacity): each system equals its own all-pairs `simulate` to
    1e-12 over a horizon shorter than the list's validity."""
    problems = [box_problem(seed=seed) for seed in range(3)]
    builder = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)
    listed = [
        eqx.tree_at(
            lambda s: s.potential,
            system,
            system.potential.with_neighbors(builder(system.potential, g0)),
        )
        for system, g0, _ in problems
    ]
    batch = jax.tree.map(lambda *leaves: jnp.stack(leaves), *listed)
    g0 = jnp.stack([g for _, g, _ in problems])
    m0 = jnp.stack([m for _, _, m in problems])
    kwargs = dict(h=H, n_steps=10, save=lievi.Save(every=10))
    sol = lievi.simulate_batch(batch, METHOD, g0, m0, system_axis=0, **kwargs)
    for i, (system, g, m) in enumerate(problems):
        reference = lievi.simulate(system, METHOD, g, m, **kwargs)
        assert jnp.max(jnp.abs(sol.g[i] - reference.g)) < 1e-12
        assert jnp.max(jnp.abs(sol.m[i] - reference.m)) < 1e-12
    assert jnp.max(jnp.abs(sol.m[0] - sol.m[1])) > 1e-2  # the systems differ


def test_jax_md_segmented_run_equals_brute_force(segmented):
    """The same run with jax-md's list (allocated once, then its compiled `update` at
    each rebuild): the same saves to 1e-12."""
    pytest.importorskip("jax_md")
    system, g0, m0, sol = segmented
    builder = lievi.JaxMDNeighbors(SKIN, capacity=CAPACITY)
    cells = lievi.simulate_with_neighbor_list(
        system,
        METHOD,
        g0,
        m0,
        h=H,
        n_steps=200,
        rebuild_every=10,
        save=lievi.Save(every=10),
        builder=builder,
    )
    assert jnp.max(jnp.abs(cells.g - sol.g)) < 1e-12
    assert jnp.max(jnp.abs(cells.m - sol.m)) < 1e-12
    assert int(cells.stats["neighbor_pairs"]) == int(sol.stats["neighbor_pairs"])


def test_linear_momentum_conserved_in_a_box(segmented):
    """Total linear momentum to 1e-12 relative (to the sum of the bodies' |P|); the
    angular momentum is not conserved (the box breaks rotation invariance)."""
    system, _, _, sol = segmented
    total = dg.total_momentum(system, sol.g, sol.m)
    scale = jnp.sum(jnp.linalg.norm(sol.m[0, :, 3:], axis=-1))
    assert jnp.max(jnp.abs(total[:, 3:] - total[0, 3:])) <= 1e-12 * scale
    assert jnp.max(jnp.abs(total[:, :3] - total[0, :3])) > 1e-6


@pytest.mark.parametrize("rebuild_after", [None, 0.5])
def test_stale_list_is_reported(rebuild_after):
    """A list built at a segment's start that goes stale within it is an error, also when
    lists are reused (the rerun with a fresh list goes stale too)."""
    system, g0, m0 = box_problem()
    builder = lievi.BruteForceNeighbors(0.01, capacity=CAPACITY)
    with pytest.raises(RuntimeError, match="smaller `rebuild_every` or a larger `skin`"):
        lievi.simulate_with_neighbor_list(
            system,
            METHOD,
            g0,
            m0,
            h=H,
            n_steps=40,
            rebuild_every=20,
            builder=builder,
            rebuild_after=rebuild_after,
        )


def test_failed_step_ends_the_run(segmented):
    """Coincident sites at the start, `throw=False`: `RESULTS.nonfinite` at step 0, the
    saves after it NaN, the shape that of the whole horizon."""
    system, g0, m0, _ = segmented
    g0 = g0.at[1].set(g0[0])
    builder = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)
    sol = lievi.simulate_with_neighbor_list(
        system, METHOD, g0, m0, h=H, n_steps=40, rebuild_every=10, builder=builder, throw=False
    )
    assert int(sol.result) == lievi.RESULTS.nonfinite and int(sol.stats["failed_step"]) == 0
    assert sol.g.shape[0] == 41 and bool(jnp.all(jnp.isnan(sol.m[1:])))
    # The error names the function that was called.
    with pytest.raises(Exception, match="simulate_with_neighbor_list: a step failed.*NaN or inf"):
        lievi.simulate_with_neighbor_list(
            system, METHOD, g0, m0, h=H, n_steps=40, rebuild_every=10, builder=builder
        )


def test_capacity_overflow_is_reported():
    system, g0, _ = box_problem()
    with pytest.raises(ValueError, match="`capacity`"):
        lievi.BruteForceNeighbors(SKIN, capacity=5)(system.potential, g0)


def test_bad_input():
    sites, lj = jnp.zeros((2, 1, 3)), lievi.LennardJones()
    with pytest.raises(ValueError, match="`box`"):
        lievi.SitePotential(sites, lj, cutoff=1.0, box=[3.0, 0.0, 3.0])
    with pytest.raises(ValueError, match="`box`"):
        lievi.SitePotential(sites, lj, cutoff=1.0, box=-3.0)
    with pytest.raises(ValueError, match="`cutoff`"):
        lievi.SitePotential(sites, lj, cutoff=2.0, box=3.0)
    with pytest.raises(ValueError, match="`cutoff`"):
        lievi.SitePotential(sites, lj, cutoff=0.0)
    with pytest.raises(ValueError, match="`cutoff`"):
        lievi.SitePotential(sites, lj, box=3.0)
    with pytest.raises(ValueError, match="`cutoff`"):
        lievi.SitePotential(sites, lj, neighbors=[[0, 1]])
    with pytest.raises(ValueError, match="`neighbors`"):
        lievi.SitePotential(sites, lj, cutoff=1.0, neighbors=[0, 1])
    with pytest.raises(ValueError, match="`neighbors`"):
        lievi.SitePotential(sites, lj, cutoff=1.0, neighbors=[[0, 3]])
    with pytest.raises(ValueError, match="one body"):
        lievi.SitePotential(jnp.zeros((2, 2, 3)), lj, cutoff=1.0, neighbors=[[0, 1]])
    with pytest.raises(ValueError, match="`skin`"):
        lievi.BruteForceNeighbors(0.0)
    with pytest.raises(ValueError, match="cut-off"):
        lievi.BruteForceNeighbors(0.1)(lievi.SitePotential(sites, lj), jnp.zeros((2, 4, 4)))
    system, g0, m0 = box_problem()
    with pytest.raises(ValueError, match="`rebuild_every`"):
        lievi.simulate_with_neighbor_list(
            system, METHOD, g0, m0, h=H, n_steps=30, rebuild_every=20, builder=None
        )
    for fraction in (0.0, 0.7):
        with pytest.raises(ValueError, match="`rebuild_after`"):
            lievi.simulate_with_neighbor_list(
                system,
                METHOD,
                g0,
                m0,
                h=H,
                n_steps=20,
                rebuild_every=10,
                builder=None,
                rebuild_after=fraction,
            )


def test_jax_md_is_optional(monkeypatch):
    """`import lievi` does not import jax-md; without it the jax-md builder says how to
    install it."""
    code = "import sys, lievi; assert 'jax_md' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
    monkeypatch.setitem(sys.modules, "jax_md", None)
    system, g0, _ = box_problem()
    with pytest.raises(ImportError, match=r'pip install "lievi\[jaxmd\]"'):
        lievi.JaxMDNeighbors(SKIN)(system.potential, g0)


@pytest.mark.slow
def test_energy_error_bounded_with_cutoff():
    """4000 steps in the periodic box, a rebuild every 5: no drift — the mean energy error
    of the second half within 1.5× the first half's (measured 1.16×; a linear drift gives
    3×) — and small, the largest 2e-2 of |E_0| (8.7e-3 measured: close encounters at
    h = 0.005; the error scales as h², 4× smaller at h/2)."""
    system, g0, m0 = box_problem()
    builder = lievi.BruteForceNeighbors(SKIN, capacity=CAPACITY)
    sol = lievi.simulate_with_neighbor_list(
        system,
        METHOD,
        g0,
        m0,
        h=H,
        n_steps=4000,
        rebuild_every=5,
        save=lievi.Save(every=5),
        builder=builder,
    )
    energy = dg.energy(system, sol.g, sol.m)
    error = jnp.abs(energy - energy[0]) / jnp.abs(energy[0])
    half = len(error) // 2
    assert jnp.max(error) < 2e-2
    assert jnp.mean(error[half:]) < 1.5 * jnp.mean(error[:half])


class _HostCandidates(lievi.AbstractNeighborBuilder):
    """A builder with `candidates` only (NumPy, every pair): its rebuilds are called back
    on the host from the run's program."""

    def candidates(self, x, body, radius, box):
        d = x[:, None] - x[None]
        if box is not None:
            d = d - box * np.round(d / box)
        near = (np.sum(d * d, -1) < radius**2) & (body[:, None] != body[None])
        return np.nonzero(np.triu(near, 1))


class _Overflowing(lievi.BruteForceNeighbors):
    """Every rebuild inside the program reports an overflow: each list is built on the
    host and the program resumed from where it stopped."""

    def rebuild(self, potential, g, state):
        pairs, state, _ = super().rebuild(potential, g, state)
        return pairs, state, jnp.asarray(True)


@pytest.mark.parametrize("builder", [_HostCandidates, _Overflowing])
def test_host_builds_equal_device_builds(segmented, builder):
    """A builder with `candidates` only, and rebuilds that overflow (the list then built on
    the host where the loop stopped, the run resumed from there): the saves and the counts
    of the fixture's run with device rebuilds, to 1e-12, over its first 40 steps."""
    system, g0, m0, sol = segmented
    run = lievi.simulate_with_neighbor_list(
        system,
        METHOD,
        g0,
        m0,
        h=H,
        n_steps=40,
        rebuild_every=10,
        save=lievi.Save(every=10),
        builder=builder(SKIN, capacity=CAPACITY),
    )
    assert int(run.result) == 0 and int(run.stats["neighbor_builds"]) == 4
    assert jnp.max(jnp.abs(run.g - sol.g[:5])) < 1e-12
    assert jnp.max(jnp.abs(run.m - sol.m[:5])) < 1e-12
