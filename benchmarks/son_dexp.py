"""Cost of the generic exponential chart on SO(n): `dexp`, its `jax.jacfwd` (what the DEP
Newton iteration evaluates), and whole DEP steps of the generalized rigid body.

For each `n` (default 4; `--n 4 5` for more) and in one process:

- `dexp`, `jacfwd(dexpinv)`, `exp`: microseconds per call inside a `lax.scan` of 2000
  calls (no Python dispatch), at an increment of a DEP step (`h·Ω`, no scaling needed)
  and at a large one (`‖ad_x‖_∞ ≈ 3`, three doublings);
- `simulate`: one body, `DEP()` (exp chart) and `DEP(chart="cayley")` for comparison,
  2000 steps of h = 0.05, the final state saved: microseconds per step;
- `simulate_batch`: 256 bodies, 200 steps: microseconds per body-step;
- the first compile of `simulate` (100 steps) in this process.

Best of 5 after a warm-up. For a before/after comparison run it once per checkout, each
in its own process, with `PYTHONPATH` set to that checkout (the script prints the
`lievi` it imported).

    python benchmarks/son_dexp.py [--n 4 5] [--out son_dexp]

Writes `benchmarks/results/<out>.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", None)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def _best(run, repeats=5):
    jax.block_until_ready(run())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run())
        times.append(time.perf_counter() - start)
    return min(times)


def _in_scan(f, x, length=2000):
    """Seconds per call of `f` inside a scan whose carry depends on each result."""

    @jax.jit
    def loop(x):
        def body(c, _):
            return c + 1e-12 * jnp.sum(f(c)), None

        return jax.lax.scan(body, x, None, length=length)[0]

    return _best(lambda: loop(x)) / length


def measure(n: int) -> dict:
    group = lievi.SOn(n)
    d = group.algebra_dim
    rng = np.random.default_rng(0)
    moments = jnp.asarray(1.0 + 0.5 * np.arange(n))
    system = lievi.GeneralizedRigidBody(moments)
    m0 = jnp.asarray(0.5 * rng.standard_normal(d))
    h = 0.05
    small = h * system.velocity(m0)
    large = small * 3.0 / float(jnp.max(jnp.sum(jnp.abs(group.ad(small)), -1)))
    row = {"n": n, "algebra_dim": d}
    for name, x in (("step increment", small), ("large (3 doublings)", large)):
        row[name] = {
            "dexp_us": 1e6 * _in_scan(group.dexp, x),
            "jacfwd_dexpinv_us": 1e6 * _in_scan(jax.jacfwd(group.dexpinv), x),
            "exp_us": 1e6 * _in_scan(group.exp, x),
        }
    g0 = jnp.eye(n)
    start = time.perf_counter()
    jax.block_until_ready(lievi.simulate(system, lievi.DEP(), g0, m0, h=h, n_steps=100).m)
    row["simulate_first_call_s"] = time.perf_counter() - start
    steps, batch, batch_steps = 2000, 256, 200
    gb = jnp.broadcast_to(g0, (batch, n, n))
    mb = m0 * (1 + 0.05 * jnp.asarray(rng.standard_normal((batch, 1))))
    for label, integrator in (("DEP exp", lievi.DEP()), ("DEP cayley", lievi.DEP(chart="cayley"))):
        one = _best(
            lambda integrator=integrator: (
                lievi.simulate(system, integrator, g0, m0, h=h, n_steps=steps, save_every=steps).m
            )
        )
        many = _best(
            lambda integrator=integrator: (
                lievi.simulate_batch(
                    system, integrator, gb, mb, h=h, n_steps=batch_steps, save_every=batch_steps
                ).m
            )
        )
        row[label] = {
            "simulate_us_per_step": 1e6 * one / steps,
            "simulate_batch_us_per_body_step": 1e6 * many / (batch * batch_steps),
        }
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[4])
    parser.add_argument("--out", default="son_dexp")
    args = parser.parse_args()
    print(f"lievi from {lievi.__file__}")
    report = {
        "description": __doc__.splitlines()[0],
        "lievi": lievi.__file__,
        "jax": jax.__version__,
        "device": str(jax.devices()[0]),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_before": os.getloadavg(),
        "rows": [],
    }
    for n in args.n:
        row = measure(n)
        report["rows"].append(row)
        print(json.dumps(row, indent=1))
    report["load_after"] = os.getloadavg()
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
