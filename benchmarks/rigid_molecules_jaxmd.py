"""Rigid three-site molecules: energy error against step size, lievi against jax-md.

One system, float64, free space: `--molecules` (default 8) rigid water-like molecules (an
"O" site of mass 16 and two "H" sites of mass 1, O–H 0.33, angle 104.5°) on a jittered
cubic lattice of spacing 1.6, random orientations, random body angular momenta and
linear momenta (total linear momentum zero). Site–site energies between sites of
different molecules, no cut-off: Lennard-Jones between O sites (`ε = 1`, `σ = 1`) and
Coulomb between all sites (charges −0.8, +0.4, +0.4, `k = 1`).

- **jax-md** (`jax_md.rigid_body`, `jax_md.simulate.nve`): the molecule is a
  `rigid_body.point_union_shape`, the energy `rigid_body.point_energy` of a site energy
  on the world positions of the sites (the pairs of different molecules, listed once as
  index arrays), the state `RigidBody(center, Quaternion)`, integrated by `simulate.nve`
  (velocity Verlet on the centres, Miller et al.'s NO_SQUISH symplectic quaternion
  scheme on the orientations), `jax.jit` around a `lax.scan` of steps.
- **lievi**: `RigidBodies` with `SitePotential((LennardJones, Coulomb))`, the same sites
  (jax-md's principal-frame points), masses and principal moments (jax-md's: each point
  carries a sphere of radius 0.5, `2/5 r² m`), `simulate` with `DEP(chart="cayley")` and
  `LiePoissonSplitting()`.

The same initial state in both (`g = [[R(q), x], [0, 1]]`, `Π` the body angular
momentum, `P = Rᵀp`); the initial energies are checked equal. For each step size `h` the
run takes `--steps` steps; the energy error is `max_k |E_k − E_0| / |E_0|`, from a run that
evaluates the energy at every step. Wall time per step is the best of `--rounds` (5)
compiled runs at each `h` of the steps alone, the final state kept (`seconds_per_step`,
`molecule_steps_per_second`; `cpu_seconds_per_step` the process's CPU time, steadier on a
loaded machine), and of the run with the energy (`seconds_per_step_with_energy`;
not like for like: jax-md evaluates its total energy inside its loop, right after the
force at the same positions, and XLA can share the site pass between the two, while
lievi's energies are `lievi.diagnostics.energy` of the saved states after the run). The
programs are timed in rounds, each calling every program once in turn, so that a
change of the machine's load falls on all of them; `speed_vs_jaxmd` is jax-md's time per
step over each method's, from the same rounds. The `uptime` at the start and end is
recorded.

With `--neighbors` (thousands of molecules, where all pairs would take gigabytes of
index arrays in either library): the molecules fill a periodic box (the lattice's period,
`1.6·⌈N^(1/3)⌉`), the site energies are cut off at `--cutoff` (2.5) and
energy-and-force shifted in both, and both use jax-md's cell list with a skin `--skin`
(0.5): jax-md as its users write it (`partition.neighbor_list` with
`dr_threshold = skin`, `rigid_body.point_energy_neighbor_list`, `nbrs.update` after each
step inside the compiled loop, the overflow flag checked after the run), lievi by
`simulate_with_neighbor_list` with `JaxMDNeighbors(skin)`, segments of
`--rebuild-every` steps and `rebuild_after=0.25`. Neither builds a list at the start of a
timed run: jax-md's is allocated once before the runs, lievi's first build at the initial
state is kept from the first (compiling) call at that state (`JaxMDNeighbors` keeps a list
built at the very same positions); the rebuilds inside the runs are timed in both (one
per 100 steps in each at 2048 molecules). Only the splitting runs on lievi's side;
the energy error is over the saves every `--save-every` steps (in lievi's, each from a list
built at the saved state), and only the runs without the energy are timed.

    python benchmarks/rigid_molecules_jaxmd.py [--molecules 8] [--steps 1000]
        [--h 0.0025 0.005 0.01 0.02] [--rounds 5] [--out rigid_molecules_jaxmd]
        [--neighbors [--cutoff 2.5] [--skin 0.5] [--rebuild-every 20] [--save-every 50]]

Needs jax-md (`pip install -e ".[jaxmd]"`). Writes `benchmarks/results/<out>.json` and
`<out>.png`.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402
from lievi import diagnostics  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results"
STEP_SIZES = (0.0025, 0.005, 0.01, 0.02)
CHARGES = np.array([-0.8, 0.4, 0.4])
MASSES = np.array([16.0, 1.0, 1.0])


def molecule_sites():
    """The three sites of one molecule, O at the origin, H–O–H 104.5° in the x–y plane."""
    half = np.deg2rad(104.5) / 2
    bond = 0.33
    return np.array(
        [[0.0, 0.0, 0.0], [bond * np.sin(half), bond * np.cos(half), 0.0],
         [-bond * np.sin(half), bond * np.cos(half), 0.0]]
    )  # fmt: skip


def initial_state(n, rng):
    """Centres, unit quaternions (w, x, y, z), body angular momenta and world linear momenta."""
    side = int(np.ceil(n ** (1 / 3)))
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    centres = 1.6 * grid + rng.uniform(-0.1, 0.1, size=(n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    angular = rng.normal(size=(n, 3)) * 0.5
    linear = rng.normal(size=(n, 3)) * 1.0
    linear -= linear.mean(axis=0)
    return centres, q, angular, linear


def molecule_shape():
    """`(sites, moments, mass)` of one molecule as `jax_md.rigid_body.point_union_shape`
    builds it (checked against it in `main`): the sites about their centre of mass,
    turned to the principal frame (`jnp.linalg.eigh`), each point a sphere of radius 0.5
    (`2/5 r² m` added to each principal moment; jax-md computes `2/5 r²` in float32, and
    so does this, for the same moments to round-off)."""
    sites = molecule_sites() - MASSES @ molecule_sites() / MASSES.sum()
    sphere = float(2 / 5 * np.float32(0.5) ** 2)
    inertia = sum(
        m * (np.dot(s, s) * np.eye(3) - np.outer(s, s) + sphere * np.eye(3))
        for m, s in zip(MASSES, sites)
    )
    moments, axes = jnp.linalg.eigh(jnp.asarray(inertia))
    return np.asarray(sites @ np.asarray(axes)), np.asarray(moments), MASSES.sum()


def lievi_molecules(n, seed=0, **cutoff_and_box):
    """`(system, g0, m0, raw)`: `n` molecules as `lievi.RigidBodies` and their initial
    state; `raw = (centres, quaternions, body angular momenta, world linear momenta)`;
    `cutoff_and_box`: `lievi.SitePotential`'s `cutoff` and `box` (default none)."""
    sites, moments, mass = molecule_shape()
    centres, q, angular, linear = initial_state(n, np.random.default_rng(seed))
    pairs = lievi.SitePotential(
        np.broadcast_to(sites, (n, 3, 3)),
        (lievi.LennardJones(epsilon=[[1.0, 0.0], [0.0, 0.0]], sigma=1.0), lievi.Coulomb()),
        types=np.tile([0, 1, 1], (n, 1)),
        charges=np.tile(CHARGES, (n, 1)),
        **cutoff_and_box,
    )
    system = lievi.RigidBodies(np.tile(moments, (n, 1)), np.full(n, mass), potential=pairs)
    R = jax.vmap(lievi.quaternion_wxyz_to_matrix)(jnp.asarray(q))
    g0 = jnp.broadcast_to(jnp.eye(4), (n, 4, 4)).at[:, :3, :3].set(R).at[:, :3, 3].set(centres)
    P = jnp.einsum("nji,nj->ni", R, jnp.asarray(linear))  # body frame
    m0 = jnp.concatenate([jnp.asarray(angular), P], axis=1)
    return system, g0, m0, (centres, q, angular, linear)


def site_energy_fn(n):
    """The site energy of `n` molecules' world site positions `(3n, 3)`: every pair of
    sites on different molecules, O–O Lennard-Jones and Coulomb (pure jnp)."""
    i, j = np.triu_indices(3 * n, k=1)
    keep = i // 3 != j // 3
    i, j = i[keep], j[keep]
    oxygen = np.arange(3 * n) % 3 == 0
    lj = oxygen[i] & oxygen[j]
    qq = np.tile(CHARGES, n)[i] * np.tile(CHARGES, n)[j]

    def energy(x):
        d = x[i] - x[j]
        r2 = jnp.sum(d * d, axis=-1)
        s6 = 1 / (r2 * r2 * r2)
        return jnp.sum(jnp.where(lj, 4 * (s6 * s6 - s6), 0.0)) + jnp.sum(qq / jnp.sqrt(r2))

    return energy


def neighbor_energy_fn(n, box, cutoff):
    """The site energy of `n` molecules over a jax-md neighbour list (`OrderedSparse`,
    each pair once), in the periodic box of side `box`, cut off at `cutoff` and
    energy-and-force shifted there as `lievi.SitePotential(cutoff=…)` shifts each pair
    energy: `e(r) − e(r_c) − (r − r_c) e'(r_c)`. Pairs of sites of one molecule are
    dropped (pure jnp, as a jax-md user writes a custom pair energy)."""
    molecule = jnp.arange(3 * n) // 3
    oxygen = jnp.arange(3 * n) % 3 == 0
    charges = jnp.tile(jnp.asarray(CHARGES), n)
    rc = cutoff

    def lennard_jones(r):
        s6 = 1 / r**6
        return 4 * (s6 * s6 - s6), -24 * (2 * s6 * s6 - s6) / r  # e, e'

    lj_c, lj_slope_c = lennard_jones(rc)

    def energy(x, neighbor, **kwargs):
        i, j = neighbor.idx
        real = i < 3 * n
        i, j = jnp.where(real, i, 0), jnp.where(real, j, 0)
        d = x[i] - x[j]
        d = d - box * jnp.round(d / box)
        r2 = jnp.sum(d * d, axis=-1)
        inside = real & (molecule[i] != molecule[j]) & (r2 < rc * rc)
        r = jnp.sqrt(jnp.where(inside, r2, rc * rc))
        lj = lennard_jones(r)[0] - lj_c - (r - rc) * lj_slope_c
        coulomb = charges[i] * charges[j] * (1 / r - 1 / rc + (r - rc) / rc**2)
        e = jnp.where(oxygen[i] & oxygen[j], lj, 0.0) + coulomb
        return jnp.sum(jnp.where(inside, e, 0.0))

    return energy


def run_jaxmd_neighbors(n, state0, steps, h, box, cutoff, skin, save_every):
    """As `run_jaxmd`, over jax-md's neighbour list in a periodic box, as its users write
    it: `partition.neighbor_list` (cell list, `OrderedSparse`, `dr_threshold = skin`: the
    list is rebuilt inside the compiled loop when a site has moved half the skin),
    `rigid_body.point_energy_neighbor_list`, `nbrs.update` after every step, an overflow
    check after the run. The energies are those at every `save_every`-th step."""
    from jax_md import partition, rigid_body, simulate, space

    shape, centres, q, angular, linear = state0
    side = jnp.asarray(box, float)
    displacement, shift = space.periodic(side)
    neighbor_fn = partition.neighbor_list(
        displacement, side, cutoff, dr_threshold=skin, capacity_multiplier=1.25,
        format=partition.OrderedSparse,
    )  # fmt: skip
    neighbor_fns, energy_fn = rigid_body.point_energy_neighbor_list(
        neighbor_energy_fn(n, box, cutoff), neighbor_fn, shape
    )
    mass = shape.mass()
    body = rigid_body.RigidBody(
        jnp.mod(jnp.asarray(centres), box), rigid_body.Quaternion(jnp.asarray(q))
    )
    conjugate = rigid_body.angular_momentum_to_conjugate_momentum(
        body.orientation, jnp.asarray(angular)
    )
    momentum = rigid_body.RigidBody(jnp.asarray(linear), conjugate)
    init_fn, apply_fn = simulate.nve(energy_fn, shift, h)
    neighbors0 = neighbor_fns.allocate(body)

    def total(state, neighbors):
        kinetic = rigid_body.kinetic_energy(state.position, state.momentum, state.mass)
        return kinetic + energy_fn(state.position, neighbors)

    def advance(carry, n_steps):
        def one(_, carry):
            state, neighbors = carry
            state = apply_fn(state, neighbor=neighbors)
            return state, neighbors.update(state.position)

        return jax.lax.fori_loop(0, n_steps, one, carry)

    def start(position, momentum, neighbors):
        state = init_fn(
            jax.random.PRNGKey(0), position, 0.0, mass=mass, momenta=momentum, neighbor=neighbors
        )
        return state, neighbors

    @jax.jit
    def trajectory(position, momentum, neighbors):
        carry = start(position, momentum, neighbors)

        def saved(carry, _):
            carry = advance(carry, save_every)
            return carry, total(*carry)

        carry, energies = jax.lax.scan(saved, carry, None, length=steps // save_every)
        return jnp.concatenate([total(*start(position, momentum, neighbors))[None], energies]), (
            carry[1].did_buffer_overflow
        )

    @jax.jit
    def final(position, momentum, neighbors):
        state, neighbors = advance(start(position, momentum, neighbors), steps)
        return state.position, state.momentum, neighbors.did_buffer_overflow

    def checked(run):
        def call():
            *out, overflow = run(body, momentum, neighbors0)
            # The overflow flag is read after the run, as jax-md's users do; a run that
            # overflowed would have to be redone with a larger list.
            assert not bool(overflow), "jax-md's neighbour list overflowed"
            return out[0] if len(out) == 1 else tuple(out)

        return call

    return checked(trajectory), checked(final)


def run_lievi_neighbors(
    system, method, g0, m0, steps, h, skin, rebuild_every, save_every, builder_type
):
    """As `run_lievi`, with `lievi.simulate_with_neighbor_list` and jax-md's cell list
    (`lievi.JaxMDNeighbors(skin)`), a list kept across segments until a site has moved a
    quarter of the skin (`rebuild_after=0.25`). The energies at every `save_every`-th step
    are each from a list built at that state (outside the timed run)."""
    builder = builder_type(skin)
    options = dict(h=h, n_steps=steps, rebuild_every=rebuild_every, builder=builder)

    def trajectory():
        sol = lievi.simulate_with_neighbor_list(
            system, method, g0, m0, **options, rebuild_after=0.25,
            save=lievi.Save(g=True, m=True, every=save_every),
        )  # fmt: skip
        energy = eqx.filter_jit(diagnostics.energy)
        energies = []
        for g, m in zip(sol.g, sol.m):
            listed = eqx.tree_at(
                lambda s: s.potential, system, system.potential.with_neighbors(
                    builder(system.potential, g)
                ),
            )  # fmt: skip
            energies.append(energy(listed, g, m))
        return jnp.stack(energies)

    def final():
        sol = lievi.simulate_with_neighbor_list(
            system, method, g0, m0, **options, rebuild_after=0.25,
            save=lievi.Save(g=True, m=True, every=steps),
        )  # fmt: skip
        return sol.g, sol.m

    return trajectory, final


def run_jaxmd(n, state0, steps, h):
    """`(energies (steps + 1,), seconds per step, seconds per step with the energy)` of
    jax-md's rigid-body NVE."""
    from jax_md import rigid_body, simulate, space

    shape, centres, q, angular, linear = state0
    _, shift = space.free()
    energy_fn = rigid_body.point_energy(site_energy_fn(n), shape)
    mass = shape.mass()
    body = rigid_body.RigidBody(jnp.asarray(centres), rigid_body.Quaternion(jnp.asarray(q)))
    conjugate = rigid_body.angular_momentum_to_conjugate_momentum(
        body.orientation, jnp.asarray(angular)
    )
    momentum = rigid_body.RigidBody(jnp.asarray(linear), conjugate)
    init_fn, apply_fn = simulate.nve(energy_fn, shift, h)

    def total(state):
        return rigid_body.kinetic_energy(state.position, state.momentum, state.mass) + energy_fn(
            state.position
        )

    def start(position, momentum):
        return init_fn(jax.random.PRNGKey(0), position, 0.0, mass=mass, momenta=momentum)

    @jax.jit
    def trajectory(position, momentum):
        state = start(position, momentum)

        def one(state, _):
            state = apply_fn(state)
            return state, total(state)

        _, energies = jax.lax.scan(one, state, None, length=steps)
        return jnp.concatenate([total(state)[None], energies])

    @jax.jit
    def final(position, momentum):
        state = jax.lax.fori_loop(0, steps, lambda _, s: apply_fn(s), start(position, momentum))
        return state.position, state.momentum

    return lambda: trajectory(body, momentum), lambda: final(body, momentum)


def run_lievi(system, method, g0, m0, steps, h):
    """As `run_jaxmd`, for `lievi.simulate` with `method`."""

    @jax.jit
    def trajectory(g0, m0):
        sol = lievi.simulate(system, method, g0, m0, h=h, n_steps=steps, save=lievi.Save())
        # One saved state at a time, as jax-md's `total` inside its scan: vectorised over
        # every save at once, the site-pair arrays of hundreds of molecules would take
        # gigabytes.
        return jax.lax.map(lambda s: diagnostics.energy(system, s[0], s[1]), (sol.g, sol.m))

    @jax.jit
    def final(g0, m0):
        sol = lievi.simulate(
            system, method, g0, m0, h=h, n_steps=steps, save=lievi.Save(every=steps)
        )
        return sol.g, sol.m

    return lambda: trajectory(g0, m0), lambda: final(g0, m0)


def _interleaved(programs, steps, rounds):
    """`{name: (best wall time, best CPU time, [wall time of each round])}` per step of
    each compiled program, timed in `rounds` rounds that call every program once in turn:
    on a shared, loaded machine the load then falls on all alike, where timing one
    program's repeats after another's compares them at different loads. The CPU time
    (`time.process_time`, this process's threads) is the steadier figure under load."""
    best = {name: [np.inf, np.inf, []] for name in programs}
    for _ in range(rounds):
        for name, run in programs.items():
            wall, cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(run())
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            best[name][:2] = [min(best[name][0], wall / steps), min(best[name][1], cpu / steps)]
            best[name][2].append(wall / steps)
    return best


def main():
    from jax_md import rigid_body

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--molecules", type=int, default=8)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--out", default="rigid_molecules_jaxmd")
    parser.add_argument("--h", type=float, nargs="+", default=list(STEP_SIZES))
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--neighbors", action="store_true",
        help="neighbour lists in a periodic box (jax-md's cell list in both)",
    )  # fmt: skip
    parser.add_argument("--cutoff", type=float, default=2.5)
    parser.add_argument("--skin", type=float, default=0.5)
    parser.add_argument("--rebuild-every", type=int, default=20)
    parser.add_argument("--save-every", type=int, default=50)
    args = parser.parse_args()
    n, steps = args.molecules, args.steps
    side = int(np.ceil(n ** (1 / 3)))
    box = 1.6 * side  # the lattice's period: a full lattice is a crystal with jitter
    neighbors = dict(cutoff=args.cutoff, box=box) if args.neighbors else {}
    load = os.getloadavg()[0]
    uptime = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    print(f"load average at start: {load:.2f}; {platform.processor() or platform.machine()}")

    system, g0, m0, (centres, q, angular, linear) = lievi_molecules(n, **neighbors)
    # The molecule as jax-md builds it: the same principal-frame sites, masses and moments.
    sites, moments, mass = molecule_shape()
    shape = rigid_body.point_union_shape(
        jnp.asarray(molecule_sites() - MASSES @ molecule_sites() / MASSES.sum()),
        jnp.asarray(MASSES),
    )
    assert np.allclose(np.asarray(shape.points), sites, atol=1e-14)
    assert np.allclose(np.asarray(shape.mass().orientation).reshape(3), moments, rtol=1e-14)
    assert np.isclose(float(np.asarray(shape.mass().center).reshape(-1)[0]), mass, rtol=1e-15)

    # The same world site positions in both.
    body = rigid_body.RigidBody(jnp.asarray(centres), rigid_body.Quaternion(jnp.asarray(q)))
    world_jaxmd, _ = rigid_body.union_to_points(body, shape)
    world_lievi = jnp.einsum("nij,kj->nki", g0[:, :3, :3], jnp.asarray(sites)) + g0[:, None, :3, 3]
    assert np.allclose(world_jaxmd, world_lievi.reshape(-1, 3), atol=1e-13)

    methods = {
        "jax-md NVE (NO_SQUISH)": None,
        "lievi DEP Cayley": lievi.DEP(chart="cayley"),
        "lievi splitting": lievi.LiePoissonSplitting(),
    }
    if args.neighbors:
        methods = {
            "jax-md NVE (NO_SQUISH), neighbour list": None,
            "lievi splitting, simulate_with_neighbor_list": lievi.LiePoissonSplitting(),
        }
    rows = []
    for h in args.h:
        programs, energies = {}, {}
        for name, method in methods.items():
            state0 = (shape, centres, q, angular, linear)
            if args.neighbors and method is None:
                trajectory, final = run_jaxmd_neighbors(
                    n, state0, steps, h, box, args.cutoff, args.skin, args.save_every
                )
            elif args.neighbors:
                trajectory, final = run_lievi_neighbors(
                    system, method, g0, m0, steps, h, args.skin, args.rebuild_every,
                    args.save_every, lievi.JaxMDNeighbors,
                )  # fmt: skip
            elif method is None:
                trajectory, final = run_jaxmd(n, state0, steps, h)
            else:
                trajectory, final = run_lievi(system, method, g0, m0, steps, h)
            # The first calls compile.
            energies[name] = np.asarray(jax.block_until_ready(trajectory()))
            jax.block_until_ready(final())
            programs[name] = final
            if not args.neighbors:  # with a list, the energies are not timed (see the runs)
                programs[name + " with energy"] = trajectory
        times = _interleaved(programs, steps, args.rounds)
        for name in methods:
            (per_step, cpu, each_round), (with_energy, *_) = (
                times[name],
                times.get(name + " with energy", [None] * 3),
            )
            error = float(np.max(np.abs(energies[name] - energies[name][0])))
            error /= abs(energies[name][0])
            rows.append(
                {
                    "method": name,
                    "h": h,
                    "energy_0": float(energies[name][0]),
                    "relative_energy_error": error,
                    "seconds_per_step": per_step,
                    "cpu_seconds_per_step": cpu,
                    "seconds_per_step_with_energy": with_energy,
                    "seconds_per_step_each_round": each_round,
                    "molecule_steps_per_second": n / per_step,
                    "finite": bool(np.all(np.isfinite(energies[name]))),
                }
            )
            print(
                f"h={h:<7g} {name:24s} E0 {energies[name][0]: .12f}  max|ΔE|/|E0| "
                f"{error:.3e}  {per_step * 1e6:8.1f} µs/step ({cpu * 1e6:8.1f} CPU)",
                flush=True,
            )
        baseline = rows[-len(methods)]
        for row in rows[-len(methods) :]:
            row["speed_vs_jaxmd"] = baseline["seconds_per_step"] / row["seconds_per_step"]
            row["cpu_speed_vs_jaxmd"] = (
                baseline["cpu_seconds_per_step"] / row["cpu_seconds_per_step"]
            )
            # Per round, jax-md's time over this method's in the same round: the median
            # of these is the figure least moved by a change of load between rounds.
            row["median_speed_vs_jaxmd"] = float(
                np.median(
                    np.asarray(baseline["seconds_per_step_each_round"])
                    / np.asarray(row["seconds_per_step_each_round"])
                )
            )
            print(
                f"h={h:<7g} {row['method']:24s} vs jax-md: median {row['median_speed_vs_jaxmd']:.3f}"
                f"×, best {row['speed_vs_jaxmd']:.3f}× (CPU {row['cpu_speed_vs_jaxmd']:.3f}×)",
                flush=True,
            )
    e0 = {r["energy_0"] for r in rows}
    assert max(e0) - min(e0) <= 1e-12 * max(abs(e) for e in e0), e0

    document = {
        "command": "python benchmarks/rigid_molecules_jaxmd.py " + " ".join(sys.argv[1:]),
        "molecules": n,
        "steps": steps,
        "neighbor_list": (
            dict(
                box=box,
                cutoff=args.cutoff,
                skin=args.skin,
                rebuild_every=args.rebuild_every,
                save_every=args.save_every,
            )
            if args.neighbors
            else None
        ),  # fmt: skip
        "dtype": "float64",
        "load_average_start": load,
        "uptime_start": uptime,
        "uptime_end": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
        "rounds": args.rounds,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_end": os.getloadavg()[0],
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "jax_md": importlib.metadata.version("jax-md"),
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.out}.json"
    path.write_text(json.dumps(document, indent=2))
    _plot(rows, RESULTS / f"{args.out}.png", n, steps)
    print(f"load average at end: {document['load_average_end']:.2f}; written {path}")


def _plot(rows, path, n, steps):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for name in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == name]
        hs = [r["h"] for r in mine]
        left.loglog(hs, [r["relative_energy_error"] for r in mine], "o-", label=name)
        right.semilogx(hs, [r["seconds_per_step"] * 1e6 for r in mine], "o-", label=name)
    left.set(xlabel="step size h", ylabel="max |E − E₀| / |E₀|",
             title=f"{n} rigid 3-site molecules, {steps} steps")  # fmt: skip
    right.set(xlabel="step size h", ylabel="wall time per step (µs)", title="cost (CPU)")
    left.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
