"""Throughput of interacting rigid bodies (`lievi.RigidBodies`) in body-steps per second.

Rows, all in one run, float64, `--steps` steps of size 0.01, final state only:

- "free SE(3) body, fast path": `simulate_batch` of `2·B` independent free
  `RigidBodySE3` bodies (the structure-of-arrays kernel `_kernels/_se3.py`): the baseline
  every ratio is taken against;
- "B two-body systems": `simulate_batch` of `B` independent binary asteroids
  (`lievi.gravitating_bodies`, two bodies of three point masses in mutual gravity) —
  `jax.vmap(simulate)` over the systems, each step kick – free step of both bodies –
  kick; `2·B` body-steps per step;
- "one system of N bodies": one `simulate` of `N` single-site Lennard-Jones bodies (all
  `N(N−1)/2` pairs: no neighbour list), `N` body-steps per step;
- "one system of N bodies, neighbour list": one `simulate_with_neighbor_list` of
  `--neighbor-bodies` (default 10⁴) single-site Lennard-Jones bodies at liquid density
  (`ρσ³ = 0.8`, temperature 0.7) in a periodic box, cut-off 2.5σ, skin 0.6σ, the list
  rebuilt every 10 steps (jax-md's cell list where jax-md is installed, else the
  brute-force builder), `h = 0.005`; the rebuilds and validity checks are inside the
  timed run. Timed alone too: one build from scratch (jax-md's `allocate`), one rebuild
  (its compiled `update`), and the same steps on one fixed list ("steps only");
- the cost of a gradient: `jax.grad` with respect to the gravitational constant `G` of a
  function of the final state of one binary (10·`--steps` steps), of
  `--gradient-systems` (default 256) binaries sharing one `G` (`simulate_batch`,
  `--steps` steps), and with respect to the
  Lennard-Jones `ε` of one system of `--gradient-bodies` (default 64) single-site bodies
  (all pairs, `--steps` steps), each against the same run forward.

Compile time is reported apart (first call minus the best of the timed calls). The load
average (`os.getloadavg`) is printed and saved with the figures: on a shared machine the
figures move with it, the ratios (same run) less.

    python benchmarks/rigid_bodies_throughput.py [--systems 1000] [--bodies 1000]
                                                 [--steps 100] [--out rigid_bodies_throughput]
                                                 [--neighbor-bodies 10000]
                                                 [--gradient-bodies 64]
                                                 [--gradient-systems 256]
                                                 [--gradient-only] [--neighbors-only]
                                                 [--methods "DEP Cayley" splitting]

`--gradient-only` runs the gradient rows alone; `--neighbors-only` the baseline and the
neighbour-list rows alone; `--methods` limits the methods. The gradient and the forward
run are timed in interleaved rounds (7), each the best of its rounds, in wall-clock and in
process CPU time (less sensitive to other jobs on the machine).

Writes `<outdir>/<out>.json` (`--outdir`, default `benchmarks/results`).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import sys
import time

import equinox as eqx
import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

H = 0.01
RESULTS = pathlib.Path(__file__).parent / "results"
SKIN = 0.6  # the neighbour-list row's
METHODS = {
    "DEP exp": lievi.DEP(),
    "DEP Cayley": lievi.DEP(chart="cayley"),
    "splitting": lievi.LiePoissonSplitting(),
}


def _timed(run, rounds=3):
    """`(best seconds, compile seconds, failed)`: the first call compiles and runs;
    `failed` counts the bodies whose `result` is not success (runs with `throw=False`)."""
    start = time.perf_counter()
    jax.block_until_ready(run())
    first = time.perf_counter() - start
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        out = jax.block_until_ready(run())
        times.append(time.perf_counter() - start)
    failed = int(jnp.sum(out.result != lievi.RESULTS.successful))
    return min(times), max(first - min(times), 0.0), failed


def binaries(n_systems, rng):
    """`n_systems` binary asteroids: random point masses and shapes, near-circular orbits."""
    masses = rng.uniform(0.3, 1.0, size=(n_systems, 2, 3))
    points = rng.uniform(-0.12, 0.12, size=(n_systems, 2, 3, 3))
    systems = jax.vmap(lambda m, p: lievi.gravitating_bodies(1.0, m, p))(
        jnp.asarray(masses), jnp.asarray(points)
    )
    mass = systems.mass  # (B, 2)
    total = jnp.sum(mass, axis=1)
    x = 1.5 * jnp.stack([-mass[:, 1], mass[:, 0]], axis=1) / total[:, None]
    speed = jnp.sqrt(total / 1.5)
    v = speed[:, None] * jnp.stack([-mass[:, 1], mass[:, 0]], axis=1) / total[:, None]
    g0 = jnp.broadcast_to(jnp.eye(4), (n_systems, 2, 4, 4)).at[:, :, 0, 3].set(x)
    spin = jnp.asarray(rng.normal(size=(n_systems, 2, 3)))
    Pi = jnp.einsum("bnij,bnj->bni", systems.tensor[..., :3, :3], spin)
    P = jnp.zeros((n_systems, 2, 3)).at[:, :, 1].set(mass * v)
    return systems, g0, jnp.concatenate([Pi, P], axis=-1)


def lennard_jones_cloud(n_bodies, rng):
    """`n_bodies` one-site bodies on a jittered cubic lattice (spacing 1.5σ), random spins."""
    side = int(np.ceil(n_bodies ** (1 / 3)))
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    positions = 1.5 * grid[:n_bodies] + rng.uniform(-0.1, 0.1, size=(n_bodies, 3))
    sites = jnp.zeros((n_bodies, 1, 3)).at[:, 0, 0].set(0.05)  # off the centre: torques
    potential = lievi.SitePotential(sites, lievi.LennardJones(1.0, 1.0))
    system = lievi.RigidBodies(jnp.ones((n_bodies, 3)), jnp.ones(n_bodies), potential=potential)
    g0 = jnp.broadcast_to(jnp.eye(4), (n_bodies, 4, 4)).at[:, :3, 3].set(jnp.asarray(positions))
    m0 = jnp.asarray(rng.normal(size=(n_bodies, 6)) * 0.1)
    return system, g0, m0


def lennard_jones_liquid(n_bodies, rng, density=0.8, temperature=0.7):
    """`n_bodies` one-site bodies at number density `density` in a periodic cube, cut-off
    2.5σ: a jittered simple-cubic lattice, Maxwell momenta of zero total."""
    box = (n_bodies / density) ** (1 / 3)
    side = int(np.ceil(n_bodies ** (1 / 3)))
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    positions = (grid[:n_bodies] + 0.5) * box / side + rng.uniform(-0.02, 0.02, (n_bodies, 3))
    sites = jnp.zeros((n_bodies, 1, 3)).at[:, 0, 0].set(0.05)  # off the centre: torques
    potential = lievi.SitePotential(sites, lievi.LennardJones(1.0, 1.0), cutoff=2.5, box=box)
    system = lievi.RigidBodies(jnp.ones((n_bodies, 3)), jnp.ones(n_bodies), potential=potential)
    g0 = jnp.broadcast_to(jnp.eye(4), (n_bodies, 4, 4)).at[:, :3, 3].set(jnp.asarray(positions))
    m0 = rng.normal(size=(n_bodies, 6)) * np.sqrt(temperature)
    m0[:, 3:] -= m0[:, 3:].mean(axis=0)
    return system, g0, jnp.asarray(m0)


def throughput_row(name, label, rate, seconds, compile_s, baseline):
    """One row of the JSON: body-steps/s of a case and its ratio to the baseline."""
    return {
        "method": name,
        "case": label,
        "body_steps_per_s": rate,
        "seconds": seconds,
        "compile_s": compile_s,
        "ratio_to_free_fast_path": rate / baseline,
    }


def neighbor_rows(args, methods, rng, baseline):
    """The neighbour-list row of each method: body-steps per second of the whole run
    (none with `--neighbor-bodies 0`)."""
    if args.neighbor_bodies < 1:
        return []
    try:
        import jax_md  # noqa: F401

        builder = lievi.JaxMDNeighbors(skin=SKIN)
    except ImportError:
        builder = lievi.BruteForceNeighbors(skin=SKIN)
    system, g0, m0 = lennard_jones_liquid(args.neighbor_bodies, rng)
    jax.block_until_ready(builder(system.potential, g0))  # compile the builder's pieces
    start = time.perf_counter()
    pairs, state = jax.block_until_ready(builder.build(system.potential, g0))
    build_s = time.perf_counter() - start
    jax.block_until_ready(builder.build(system.potential, g0, state)[0])
    start = time.perf_counter()
    jax.block_until_ready(builder.build(system.potential, g0, state)[0])
    rebuild_s = time.perf_counter() - start
    n_pairs = int(jnp.sum(pairs[:, 1] < args.neighbor_bodies))
    print(
        f"{type(builder).__name__}: {n_pairs} pairs within {2.5 + SKIN:.2g}σ, one build "
        f"{build_s:.3g} s, one rebuild {rebuild_s:.3g} s, box side "
        f"{float(system.potential.box[0]):.4g}σ"
    )
    listed = eqx.tree_at(lambda s: s.potential, system, system.potential.with_neighbors(pairs))
    rows = []
    for name, method in methods.items():
        label = f"one system of {args.neighbor_bodies} LJ bodies, neighbour list"

        def run(method=method):
            return lievi.simulate_with_neighbor_list(
                system,
                method,
                g0,
                m0,
                h=0.005,
                n_steps=args.steps,
                rebuild_every=args.rebuild_every,
                save=lievi.Save(every=args.steps),
                builder=builder,
                rebuild_after=args.rebuild_after,
            )

        # One warm-up run (compiles), one timed: each run is minutes at 10⁴ bodies.
        start = time.perf_counter()
        jax.block_until_ready(run())
        first = time.perf_counter() - start
        start = time.perf_counter()
        sol = jax.block_until_ready(run())
        seconds = time.perf_counter() - start
        compile_s = max(first - seconds, 0.0)
        assert int(sol.result) == lievi.RESULTS.successful
        steps_only, _, _ = _timed(
            lambda method=method: lievi.simulate(
                listed,
                method,
                g0,
                m0,
                h=0.005,
                n_steps=args.steps,
                save=lievi.Save(every=args.steps),
            ),
            rounds=1,
        )
        rate = args.neighbor_bodies * args.steps / seconds
        rows.append(
            {
                **throughput_row(name, label, rate, seconds, compile_s, baseline),
                "builder": type(builder).__name__,
                "pairs_at_start": n_pairs,
                "list_capacity": int(sol.stats["neighbor_capacity"]),
                "builds_per_run": int(sol.stats["neighbor_builds"]),
                "rebuild_after": args.rebuild_after,
                "reruns_per_run": int(sol.stats["neighbor_reruns"]),
                "one_build_s": build_s,
                "one_rebuild_s": rebuild_s,
                "steps_only_body_steps_per_s": args.neighbor_bodies * args.steps / steps_only,
                "max_site_displacement": float(sol.stats["neighbor_max_displacement"]),
                "h": 0.005,
                "rebuild_every": args.rebuild_every,
                "skin": SKIN,
                "cutoff": 2.5,
                "density": 0.8,
            }
        )
        print(
            f"{name:11s} {label:52s} {rate:10.3g} body-steps/s ({rate / baseline:.3g}× the "
            f"baseline), compile {compile_s:.1f} s, {rows[-1]['builds_per_run']} builds/run "
            f"({rows[-1]['reruns_per_run']} reruns); "
            f"steps only {rows[-1]['steps_only_body_steps_per_s']:.3g} body-steps/s; largest "
            f"site displacement {rows[-1]['max_site_displacement']:.3g} (skin/2 = {SKIN / 2})"
        )
    return rows


def gradient_row(name, label, final, x):
    """`jax.grad(final)` at `x` against `final` itself, both compiled, in 7 interleaved
    rounds, each the best of its rounds (wall clock and process CPU time)."""
    forward, gradient = jax.jit(final), jax.jit(jax.grad(final))
    fns = {"forward": forward, "gradient": gradient}
    for fn in fns.values():
        jax.block_until_ready(fn(x))
    wall = {label: [] for label in fns}
    cpu = {label: [] for label in fns}
    for _ in range(7):
        for key, fn in fns.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(x))
            wall[key].append(time.perf_counter() - start)
            cpu[key].append(time.process_time() - start_cpu)
    times = {key: min(wall[key]) for key in fns}
    cpu_ratio = min(cpu["gradient"]) / min(cpu["forward"])
    ratio = times["gradient"] / times["forward"]
    print(
        f"{name:11s} {label}: forward {times['forward']:.3g} s, gradient "
        f"{times['gradient']:.3g} s ({ratio:.2f}×; CPU time {cpu_ratio:.2f}×)"
    )
    return {
        "method": name,
        "case": label,
        "forward_s": times["forward"],
        "gradient_s": times["gradient"],
        "gradient_over_forward": ratio,
        "gradient_over_forward_cpu_time": cpu_ratio,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", type=int, default=1000)
    parser.add_argument("--bodies", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--out", default="rigid_bodies_throughput")
    parser.add_argument("--outdir", type=pathlib.Path, default=RESULTS)
    parser.add_argument("--neighbor-bodies", type=int, default=10_000)
    parser.add_argument("--gradient-only", action="store_true")
    parser.add_argument("--gradient-bodies", type=int, default=64)
    parser.add_argument("--gradient-systems", type=int, default=256)
    parser.add_argument("--neighbors-only", action="store_true")
    parser.add_argument("--rebuild-every", type=int, default=10, help="steps per segment")
    parser.add_argument(
        "--rebuild-after",
        type=float,
        default=None,
        help="`simulate_with_neighbor_list(rebuild_after=)`: keep lists across segments",
    )
    parser.add_argument("--methods", nargs="+", choices=tuple(METHODS), default=tuple(METHODS))
    args = parser.parse_args()
    methods = {name: METHODS[name] for name in args.methods}
    rng = np.random.default_rng(0)
    load = os.getloadavg()[0]
    print(
        f"load average at start: {load:.2f}; {platform.processor() or platform.machine()}; "
        f"{jax.devices()[0].device_kind} ({jax.default_backend()})"
    )
    rows = []

    free_bodies = 2 * args.systems
    inertia = jnp.asarray(rng.uniform(0.5, 2.0, size=(free_bodies, 3)))
    free = jax.vmap(lambda J: lievi.RigidBodySE3(J, 1.0))(inertia)
    g_free = jnp.broadcast_to(jnp.eye(4), (free_bodies, 4, 4))
    m_free = jnp.asarray(rng.normal(size=(free_bodies, 6)))
    systems, g_bin, m_bin = binaries(args.systems, rng)
    cloud, g_cloud, m_cloud = lennard_jones_cloud(args.bodies, rng)

    if not args.gradient_only:
        # The baseline: the free SE(3) body's structure-of-arrays fast path (DEP, Cayley chart).
        seconds, compile_s, _ = _timed(
            lambda: lievi.simulate_batch(
                free,
                lievi.DEP(chart="cayley"),
                g_free,
                m_free,
                h=H,
                n_steps=args.steps,
                save=lievi.Save(g=False, m=False, stats=False, every=args.steps),
            )
        )
        baseline = free_bodies * args.steps / seconds
        rows.append(
            {
                "method": "DEP Cayley",
                "case": f"{free_bodies} free SE(3) bodies, fast path (baseline)",
                "body_steps_per_s": baseline,
                "seconds": seconds,
                "compile_s": compile_s,
                "ratio_to_free_fast_path": 1.0,
            }
        )
        print(f"{'DEP Cayley':11s} {rows[-1]['case']:52s} {baseline:10.3g} body-steps/s")
        rows += neighbor_rows(args, methods, rng, baseline)
    if not (args.gradient_only or args.neighbors_only):
        for name, method in methods.items():
            cases = (
                (
                    f"{args.systems} two-body systems (simulate_batch)",
                    2 * args.systems,
                    lambda m=method: lievi.simulate_batch(
                        systems,
                        m,
                        g_bin,
                        m_bin,
                        h=H,
                        n_steps=args.steps,
                        save=lievi.Save(g=False, m=False, stats=False, every=args.steps),
                        throw=False,
                    ),
                ),
                (
                    f"one system of {args.bodies} Lennard-Jones bodies (all pairs)",
                    args.bodies,
                    lambda m=method: lievi.simulate(
                        cloud,
                        m,
                        g_cloud,
                        m_cloud,
                        h=H,
                        n_steps=args.steps,
                        save=lievi.Save(every=args.steps),
                    ),
                ),
            )
            for label, bodies, run in cases:
                seconds, compile_s, failed = _timed(run)
                rate = bodies * args.steps / seconds
                rows.append(throughput_row(name, label, rate, seconds, compile_s, baseline))
                rows[-1]["failed_systems"] = failed
                print(
                    f"{name:11s} {label:52s} {rate:10.3g} body-steps/s ({rate / baseline:.3g}× the "
                    f"baseline), compile {compile_s:.1f} s"
                    + (f", {failed} FAILED" if failed else "")
                )

    # Gradient cost: d/dG of a function of the final state of one binary asteroid,
    # `--steps` × 10 steps, and d/dε of one system of `--gradient-bodies` Lennard-Jones
    # bodies (all pairs), `--steps` steps, each against its forward run (the same compiled
    # run without `grad`).
    system, g0, m0 = systems, g_bin[0], m_bin[0]
    one = jax.tree.map(lambda x: x[0], system)
    n_steps = 10 * args.steps
    cloud, g_cloud, m_cloud = lennard_jones_cloud(args.gradient_bodies, rng)
    batch, g_batch, m_batch = binaries(args.gradient_systems, rng)
    for name, method in methods.items() if not args.neighbors_only else ():

        def binary_final(G, method=method):
            coupled = eqx.tree_at(lambda s: s.potential.G, one, G)
            sol = lievi.simulate(
                coupled, method, g0, m0, h=H, n_steps=n_steps, save=lievi.Save(every=n_steps)
            )
            return jnp.sum(sol.m[-1] ** 2) + jnp.sum(sol.g[-1, :, :3, 3] ** 2)

        def cloud_final(epsilon, method=method):
            coupled = eqx.tree_at(lambda s: s.potential.pair[0].epsilon, cloud, epsilon)
            sol = lievi.simulate(
                coupled,
                method,
                g_cloud,
                m_cloud,
                h=H,
                n_steps=args.steps,
                save=lievi.Save(every=args.steps),
            )
            return jnp.sum(sol.m[-1] ** 2) + jnp.sum(sol.g[-1, :, :3, 3] ** 2)

        def binaries_final(G, method=method):
            # One `G` for the whole ensemble (a parameter fitted from many observed systems).
            shared = jnp.full(batch.potential.G.shape, G)
            coupled = eqx.tree_at(lambda s: s.potential.G, batch, shared)
            sol = lievi.simulate_batch(
                coupled,
                method,
                g_batch,
                m_batch,
                h=H,
                n_steps=args.steps,
                save=lievi.Save(every=args.steps),
            )
            return jnp.sum(sol.m[:, -1] ** 2) + jnp.sum(sol.g[:, -1, :, :3, 3] ** 2)

        cases = (
            (f"gradient d/dG, one binary, {n_steps} steps", binary_final),
            (
                f"gradient d/dG, {args.gradient_systems} binaries (simulate_batch), "
                f"{args.steps} steps",
                binaries_final,
            ),
            (
                f"gradient d/dε, {args.gradient_bodies} Lennard-Jones bodies (all pairs), "
                f"{args.steps} steps",
                cloud_final,
            ),
        )
        for label, final in cases:
            rows.append(gradient_row(name, label, final, jnp.asarray(1.0)))

    document = {
        "command": "python benchmarks/rigid_bodies_throughput.py " + " ".join(sys.argv[1:]),
        "steps": args.steps,
        "h": H,
        "dtype": "float64",
        "load_average_start": load,
        "load_average_end": os.getloadavg()[0],
        "device": f"{jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}",
        "rows": rows,
    }
    args.outdir.mkdir(parents=True, exist_ok=True)
    path = args.outdir / f"{args.out}.json"
    path.write_text(json.dumps(document, indent=2))
    print(f"load average at end: {document['load_average_end']:.2f}; written {path}")


if __name__ == "__main__":
    main()
