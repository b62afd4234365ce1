"""Compile times of `lievi.simulate` and `lievi.simulate_batch`, per system and integrator.

For every system × integrator pair that applies (an integrator that does not apply to a
system raises at its first call and is listed as skipped), measured by wall clock in one
process with JAX's persistent compilation cache off and `jax.clear_caches()` before each
pair:

- `first`: the first call (`n_steps`, `save_every = 1`) minus the second, identical call:
  the compile time a new script pays (tracing, lowering, XLA);
- `n_steps`: the first call with `2·n_steps` minus a repeat of it: what changing the
  horizon costs;
- `save_every`: the first call with `2·n_steps` and `save_every = 2` minus a repeat;
- `run`: the repeat of the first call (the run time of `n_steps` steps, checks included).

Each for `simulate` (one body) and `simulate_batch` (`--batch` bodies, every save of
`g` and `m` kept: the same `save_every` is passed to both). Differences of two wall-clock
times: a figure of a few milliseconds is "nothing compiled", within the scatter of the
machine's load (printed with the results).

    python benchmarks/compile_time.py [--quick] [--steps 100] [--batch 64] [--out compile_time]
                                      [--integrators RKMK5 RKMK8]
                                      [--systems "RigidBodySE3 (free)"]
    python benchmarks/compile_time.py --throughput [--out compile_time_throughput]

Writes `benchmarks/results/<out>.json` (after each pair, so that a run cut short keeps
what it measured). `--quick`: the free rigid body on SO(3) and on SE(3) with `DEP` (exp
chart) only.

`--throughput`: run times only (the best of 5 after a warm-up), to check that the loop
in blocks (`lievi/_horizon.py`) costs nothing: `simulate_batch` on 10⁴ free rigid bodies,
100 steps, the final state saved, through the fast path (DEP exp, Lie–Poisson splitting);
`simulate` of one body for 10⁴ steps, every step saved (DEP exp, SO(3) and SE(3)), and
on SE(3) every 100th step and the final state only; one SE(3) body over 100 steps,
the final state only, and `simulate_batch` of 64 SE(3) bodies over 100 steps, the final
state only: the cost of an eager call itself.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import time

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", None)  # nothing persisted between runs

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def systems():
    """`name → (system, g0, m0)`: one body (or one system of bodies) each, a generic
    momentum."""
    so3 = (jnp.eye(3), jnp.array([0.3, -0.2, 0.5]))
    return {
        "RigidBody (free)": (lievi.RigidBody(jnp.array([1.0, 2.0, 3.0])), *so3),
        "RigidBody (heavy top)": (
            lievi.heavy_top(jnp.array([1.0, 2.0, 3.0]), 1.0, jnp.array([0.0, 0.1, 0.3])),
            *so3,
        ),
        "GeneralizedRigidBody SO(4)": (
            lievi.GeneralizedRigidBody(jnp.array([1.0, 1.5, 2.0, 2.5])),
            jnp.eye(4),
            jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4]),
        ),
        "RigidBodySE3 (free)": (
            lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0),
            jnp.eye(4),
            jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4]),
        ),
        "RigidBodies (binary)": binary(),
    }


def binary():
    """Two bodies of three point masses each (masses 2.4 and 1.2) in mutual gravity
    (`lievi.gravitating_bodies`, on SE(3)², G = 1) on a circular mutual orbit 1.5 apart
    about their barycentre at rest (a period is 122 steps of 0.05), spinning slowly."""
    points = jnp.array(
        [
            [[0.12, 0.0, 0.0], [-0.1, 0.08, 0.0], [0.0, -0.06, 0.09]],
            [[0.1, 0.0, 0.02], [-0.08, 0.07, 0.0], [0.0, -0.05, -0.08]],
        ]
    )
    bodies = lievi.gravitating_bodies(1.0, jnp.array([[1.0, 0.6, 0.8], [0.5, 0.4, 0.3]]), points)
    # Relative speed sqrt(G (m₁ + m₂)/d) = sqrt(2.4); each body's share by the other's mass.
    x, momentum = jnp.array([-0.5, 1.0]), 2.4 * 1.2 / 3.6 * jnp.sqrt(2.4)
    g0 = jnp.tile(jnp.eye(4), (2, 1, 1)).at[:, 0, 3].set(x)
    m0 = jnp.array(
        [[0.003, 0.005, 0.01, 0.0, -momentum, 0.0], [0.004, -0.002, 0.001, 0.0, momentum, 0.0]]
    )
    return bodies, g0, m0


def integrators():
    return {
        "DEP exp": lievi.DEP(chart="exp"),
        "DEP cayley": lievi.DEP(chart="cayley"),
        "MoserVeselov": lievi.MoserVeselov(),
        "LiePoissonSplitting": lievi.LiePoissonSplitting(),
        "RK4": lievi.RK4(),
        "RKMK4": lievi.RKMK4(),
        "RKMK5": lievi.RKMK5(),
        "RKMK8": lievi.RKMK8(),
        "Composition(DEP exp, 4)": lievi.Composition(lievi.DEP(chart="exp"), order=4),
        "PreprocessedMoserVeselov": lievi.PreprocessedMoserVeselov(),
    }


QUICK = {("RigidBody (free)", "DEP exp"), ("RigidBodySE3 (free)", "DEP exp")}


def timed(fn) -> float:
    """Wall-clock seconds of `fn()`, its result ready."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - start


def measure(call, steps: int) -> dict:
    """Compile and run times of `call(n_steps, save_every)` (see the module docstring)."""
    first = timed(lambda: call(steps, 1))
    run = timed(lambda: call(steps, 1))
    longer = timed(lambda: call(2 * steps, 1))
    longer_run = timed(lambda: call(2 * steps, 1))
    saving = timed(lambda: call(2 * steps, 2))
    saving_run = timed(lambda: call(2 * steps, 2))
    return {
        "first": first - run,
        "n_steps": longer - longer_run,
        "save_every": saving - saving_run,
        "run": run,
    }


def batch_momenta(m0, batch: int):
    """`batch` momenta within about 10 % of `m0` (the batches of `simulate_batch` here)."""
    key = jax.random.PRNGKey(0)
    return m0 * (1 + 0.1 * jax.random.normal(key, (batch, *m0.shape), m0.dtype))


def pair(system, integrator, g0, m0, steps: int, batch: int) -> dict:
    ms = batch_momenta(m0, batch)

    def one(n_steps, save_every):
        return lievi.simulate(
            system, integrator, g0, m0, h=0.05, n_steps=n_steps, save_every=save_every
        )

    def many(n_steps, save_every):
        return lievi.simulate_batch(
            system, integrator, g0, ms, h=0.05, n_steps=n_steps, save_every=save_every
        )

    return {
        "simulate": measure(one, steps),
        "simulate_batch": measure(many, steps),
        "fast_path": lievi.has_fast_path(system, integrator),
    }


def throughput() -> list[dict]:
    """Best-of-5 run times (see the module docstring)."""
    body = lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))
    se3 = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
    momenta = jax.random.normal(jax.random.PRNGKey(0), (10_000, 3))
    m0, m0_se3 = jnp.array([0.3, -0.2, 0.5]), jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])
    momenta_se3 = m0_se3 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(1), (64, 6)))
    bodies, g0_binary, m0_binary = binary()
    many = lievi.RigidBodies(jnp.tile(jnp.array([1.0, 2.0, 3.0]), (10_000, 1)), jnp.ones(10_000))
    g0_many = jnp.tile(jnp.eye(4), (10_000, 1, 1)).at[:, 0, 3].set(jnp.arange(10_000.0))
    m0_many = 0.1 * jax.random.normal(jax.random.PRNGKey(2), (10_000, 6))
    cases = {
        "simulate_batch 1e4 bodies x 100 steps, DEP exp": lambda: lievi.simulate_batch(
            body, lievi.DEP(), jnp.eye(3), momenta, h=0.05, n_steps=100, save=("g", "m")
        ),
        "simulate_batch 1e4 bodies x 100 steps, splitting": lambda: lievi.simulate_batch(
            body, lievi.LiePoissonSplitting(), jnp.eye(3), momenta, h=0.05, n_steps=100
        ),
        "simulate 1e4 steps, SO(3) DEP exp": lambda: lievi.simulate(
            body, lievi.DEP(), jnp.eye(3), m0, h=0.05, n_steps=10_000
        ),
        "simulate 1e4 steps, SE(3) DEP exp": lambda: lievi.simulate(
            se3, lievi.DEP(), jnp.eye(4), m0_se3, h=0.05, n_steps=10_000
        ),
        "simulate 1e4 steps, SE(3) DEP exp, every 100th saved": lambda: lievi.simulate(
            se3, lievi.DEP(), jnp.eye(4), m0_se3, h=0.05, n_steps=10_000, save_every=100
        ),
        "simulate 1e4 steps, SE(3) DEP exp, final state": lambda: lievi.simulate(
            se3, lievi.DEP(), jnp.eye(4), m0_se3, h=0.05, n_steps=10_000, save_every=10_000
        ),
        # A system of two bodies (one system: its programs take the small-run options).
        "simulate 1e4 steps, binary DEP exp, every 100th saved": lambda: lievi.simulate(
            bodies, lievi.DEP(), g0_binary, m0_binary, h=0.05, n_steps=10_000, save_every=100
        ),
        "simulate 1e4 steps, binary splitting, every 100th saved": lambda: lievi.simulate(
            bodies,
            lievi.LiePoissonSplitting(),
            g0_binary,
            m0_binary,
            h=0.05,
            n_steps=10_000,
            save_every=100,
        ),
        # One system of 10⁴ free bodies: a save is 1.8 MB, so a block holds few saves.
        "simulate 100 steps, 1e4 free RigidBodies, splitting, every 10th saved": lambda: (
            lievi.simulate(
                many,
                lievi.LiePoissonSplitting(),
                g0_many,
                m0_many,
                h=0.05,
                n_steps=100,
                save_every=10,
            )
        ),  # fmt: skip
        # A short batch run: its eager call's own cost is a large part of it.
        "simulate_batch 64 SE(3) bodies x 100 steps, DEP exp, final state": lambda: (
            lievi.simulate_batch(
                se3, lievi.DEP(), jnp.eye(4), momenta_se3, h=0.05, n_steps=100, save=("g", "m")
            )
        ),
        # 100 steps run in under 1 ms under jit: the rest is the eager call's own cost.
        "simulate 100 steps, SE(3) DEP exp, final state (the per-call cost)": lambda: (
            lievi.simulate(
                se3, lievi.DEP(), jnp.eye(4), m0_se3, h=0.05, n_steps=100, save_every=100
            )
        ),
    }
    rows = []
    for name, run in cases.items():
        timed(run)
        best = min(timed(run) for _ in range(5))
        rows.append({"case": name, "best_s": best})
        print(f"{name:50s} {1e3 * best:8.2f} ms", flush=True)
    return rows


def _write(options, out: dict) -> None:
    out["uptime"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{options.out}.json"
    path.write_text(json.dumps(out, indent=1, default=float))
    return path


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--throughput", action="store_true")
    parser.add_argument("--out", default=None)
    parser.add_argument(
        "--integrators", nargs="+", choices=list(integrators()), help="only these (default: all)"
    )
    parser.add_argument("--systems", nargs="+", help="only these (default: all)")
    options = parser.parse_args()
    options.out = options.out or (
        "compile_time_throughput" if options.throughput else "compile_time"
    )
    out = {
        "description": __doc__.splitlines()[0],
        "steps": options.steps,
        "batch": options.batch,
        "dtype": "float64",
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_before": os.getloadavg(),
    }
    if options.throughput:
        out["rows"] = throughput()
        print(f"wrote {_write(options, out)}; {out['uptime']}")
        return
    rows = out["rows"] = []
    for system_name, (system, g0, m0) in systems().items():
        for name, integrator in integrators().items():
            if options.quick and (system_name, name) not in QUICK:
                continue
            if options.integrators and name not in options.integrators:
                continue
            if options.systems and system_name not in options.systems:
                continue
            jax.clear_caches()
            row = {"system": system_name, "integrator": name}
            try:
                row.update(pair(system, integrator, g0, m0, options.steps, options.batch))
            except (ValueError, TypeError, NotImplementedError) as error:
                # Raised by the first call's checks, before anything is compiled.
                print(f"{system_name:28s} {name:26s} skipped: {str(error)[:70]}")
                continue
            rows.append(row)
            print(
                f"{system_name:28s} {name:26s} "
                + "  ".join(
                    f"{entry}: first {row[entry]['first']:5.2f} s, n_steps "
                    f"{row[entry]['n_steps']:5.2f} s, save_every {row[entry]['save_every']:5.2f}"
                    f" s, run {1e3 * row[entry]['run']:6.1f} ms"
                    for entry in ("simulate", "simulate_batch")
                ),
                flush=True,
            )
            _write(options, out)
    out.update(
        worst_first_compile_s=max(
            max(r["simulate"]["first"], r["simulate_batch"]["first"]) for r in rows
        ),
        worst_recompile_s=max(
            max(r[e][k] for e in ("simulate", "simulate_batch") for k in ("n_steps", "save_every"))
            for r in rows
        ),
    )
    path = _write(options, out)
    print(f"load before {np.round(out['load_before'], 2)}; {out['uptime']}")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
