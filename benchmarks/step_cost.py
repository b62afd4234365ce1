"""Cost of one integrator step, single body and vmapped batch, compile time apart.

Measures, for each integrator of the core library on the HLW rigid body (float64, CPU or
whatever device JAX picks): compile time of `simulate`, body-steps per second for one
body and for a vmapped batch, and the ratio to a baseline measured in the same run — an
explicit first-order Lie–Euler step (`Π ← Π + hΠ×Ω`, `g ← g exp(hΩ)`), the cheapest thing
one could write. Writes `benchmarks/results/step_cost.json`.

    python benchmarks/step_cost.py [--batch 1000] [--steps 1000]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402


class LieEuler(lievi.AbstractIntegrator):
    """Baseline: explicit Euler on the momentum, exact exponential on the group."""

    def order(self):
        return 1

    def step(self, system, g, m, h):
        xi = system.velocity(m)
        m_next = m + h * system.group.ad(xi).T @ m
        zero = jnp.zeros((), jnp.int32)
        return (
            g @ system.group.exp(h * xi),
            m_next,
            lievi.StepInfo(zero, zero, jnp.zeros((), m.dtype)),
        )


def timed(fn, *args):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best = np.inf
    for _ in range(3):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return first - best, best


def measure(integrator, batch: int, steps: int):
    body = lievi.RigidBody(jnp.array([2.0, 1.0, 2 / 3]))
    rng = np.random.default_rng(0)
    momenta = jnp.asarray(rng.normal(size=(batch, 3)))

    def final(m0):
        sol = lievi.simulate(
            body, integrator, jnp.eye(3), m0, h=0.1, n_steps=steps, save_every=steps, throw=False
        )
        return sol.m[-1]

    single = jax.jit(final)
    batched = jax.jit(jax.vmap(final))
    compile_single, run_single = timed(single, momenta[0])
    compile_batch, run_batch = timed(batched, momenta)
    return {
        "compile_s": compile_single,
        "compile_batched_s": compile_batch,
        "single_body_steps_per_s": steps / run_single,
        "batched_body_steps_per_s": batch * steps / run_batch,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()

    rows = {
        "Lie–Euler baseline": LieEuler(),
        "DEP exp": lievi.DEP(chart="exp"),
        "DEP cayley": lievi.DEP(chart="cayley"),
    }
    results = {name: measure(integ, args.batch, args.steps) for name, integ in rows.items()}
    base = results["Lie–Euler baseline"]
    device = str(jax.devices()[0])
    print(f"device: {device}, float64, batch {args.batch}, {args.steps} steps, final state only")
    print(
        f"{'integrator':<20}{'compile [s]':>12}{'1 body [st/s]':>16}{'batch [st/s]':>16}{'vs baseline':>13}"
    )
    for name, r in results.items():
        r["batched_ratio_to_baseline"] = (
            r["batched_body_steps_per_s"] / base["batched_body_steps_per_s"]
        )
        print(
            f"{name:<20}{r['compile_s']:>12.2f}{r['single_body_steps_per_s']:>16.3g}"
            f"{r['batched_body_steps_per_s']:>16.3g}{r['batched_ratio_to_baseline']:>13.3g}"
        )
    out = pathlib.Path(__file__).parent / "results" / "step_cost.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(
        json.dumps(
            {"device": device, "batch": args.batch, "steps": args.steps, "results": results},
            indent=2,
        )
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
