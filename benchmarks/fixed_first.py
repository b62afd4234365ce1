"""What leaving the Newton loop out of the SE(3) DEP kernel saves, per batch size.

Eager runs of up to `lievi._simulate_kernel.FIXED_FIRST_MAX_BODIES` bodies first compile
the kernel without the loop that follows its fixed Newton iterations. This script times
the two programs side by side, so that the rule's threshold rests on a recorded figure:
for each batch size and chart, the first `simulate_batch` call (`simulate` for one body)
with `DEP(chart=...)` (the whole kernel) and with `DEP(chart=..., max_steps=fixed)` (the
kernel without its loop, the program the rule tries first), the rule itself switched off
(threshold 0) so that each call compiles only the program named. Compile time is
the first call minus the best of 3 repeats; run time is microseconds per body-step of
200 steps of 0.05, the final state saved. Free `RigidBodySE3`, momenta within 5 % of one
value, float64, one process, `jax.clear_caches()` before each first call.

    python benchmarks/fixed_first.py [--batches 1 64 256 1024 4096] [--out fixed_first]

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
from lievi import _simulate_kernel  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
STEPS = 200


def timed(call) -> tuple[float, float]:
    """`(compile s, run µs per call)`: the first call minus the best of 3 repeats."""
    jax.clear_caches()
    start = time.perf_counter()
    jax.block_until_ready(call())
    first = time.perf_counter() - start
    best = np.inf
    for _ in range(3):
        start = time.perf_counter()
        jax.block_until_ready(call())
        best = min(best, time.perf_counter() - start)
    return first - best, best


def case(body, integrator, m0, batch: int) -> dict:
    momenta = m0 * (1 + 0.05 * np.random.default_rng(0).standard_normal((batch, m0.size)))
    momenta = jnp.asarray(momenta)
    g0 = jnp.broadcast_to(jnp.eye(4), (batch, 4, 4))

    def call():
        if batch == 1:
            return lievi.simulate(body, integrator, g0[0], momenta[0], h=0.05, n_steps=STEPS)
        return lievi.simulate_batch(body, integrator, g0, momenta, h=0.05, n_steps=STEPS)

    limit = _simulate_kernel.FIXED_FIRST_MAX_BODIES
    _simulate_kernel.FIXED_FIRST_MAX_BODIES = 0
    try:
        compile_s, run_s = timed(call)
    finally:
        _simulate_kernel.FIXED_FIRST_MAX_BODIES = limit
    return {"compile_s": compile_s, "us_per_body_step": 1e6 * run_s / (STEPS * batch)}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--batches", type=int, nargs="+", default=(1, 64, 256, 1024, 4096))
    parser.add_argument("--out", default="fixed_first")
    args = parser.parse_args()
    body = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
    m0 = np.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])
    rows = []
    for chart in ("exp", "cayley"):
        fixed = lievi.DEP(chart=chart).batch_kernel(body).fixed_iterations_only().max_steps
        for batch in args.batches:
            row = {"chart": chart, "batch": batch}
            row["with_loop"] = case(body, lievi.DEP(chart=chart), m0, batch)
            row["without_loop"] = case(body, lievi.DEP(chart=chart, max_steps=fixed), m0, batch)
            row["saved_s"] = row["with_loop"]["compile_s"] - row["without_loop"]["compile_s"]
            rows.append(row)
            print(
                f"{chart:6s} batch {batch:5d}: compile {row['with_loop']['compile_s']:.2f} s "
                f"with the loop, {row['without_loop']['compile_s']:.2f} s without "
                f"(saves {row['saved_s']:.2f} s); run "
                f"{row['with_loop']['us_per_body_step']:.3f} / "
                f"{row['without_loop']['us_per_body_step']:.3f} µs a body-step",
                flush=True,
            )
    out = {
        "description": __doc__.splitlines()[0],
        "steps": STEPS,
        "jax": jax.__version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load": os.getloadavg(),
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.out}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
