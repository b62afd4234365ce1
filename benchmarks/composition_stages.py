"""Compile and run time of `Composition` on the fast path, one body and a batch.

For compositions of order 4, 6 and 8 of the Lie–Poisson splitting and of order 4 and 6
of DEP (exp chart), on the free rigid body `I = (1, 2, 3)`, float64, `h = 0.05`: one body
over 1000 steps (`simulate`) and 10⁴ bodies over 100 steps (`simulate_batch`), each
inside `jax.jit`, the final attitude only. Compile time is the first call less the best
of 5 timed calls; run time is the best of 5. Run it on two trees (e.g. with
`PYTHONPATH=<other checkout>`) one after the other to compare them.

    python benchmarks/composition_stages.py [--out composition_stages]

Writes `benchmarks/results/<out>.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def _timed(f) -> float:
    start = time.perf_counter()
    jax.block_until_ready(f())
    return time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="composition_stages")
    options = parser.parse_args()
    body = lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))
    m0 = jnp.array([0.3, -0.2, 0.5])
    momenta = jax.random.normal(jax.random.PRNGKey(0), (10_000, 3))
    cases = [("splitting", lievi.LiePoissonSplitting(), o) for o in (4, 6, 8)]
    cases += [("DEP", lievi.DEP(), o) for o in (4, 6)]
    rows = []
    for label, inner, order in cases:
        method = lievi.Composition(inner, order=order)

        def one(m0, method=method):
            return lievi.simulate(body, method, jnp.eye(3), m0, h=0.05, n_steps=1000).g[-1]

        def many(momenta, method=method):
            sol = lievi.simulate_batch(body, method, jnp.eye(3), momenta, h=0.05, n_steps=100)
            return sol.g[:, -1]

        for name, f, arg in (("one body x 1000", one, m0), ("1e4 bodies x 100", many, momenta)):
            f = jax.jit(f)
            first = _timed(lambda f=f, arg=arg: f(arg))
            best = min(_timed(lambda f=f, arg=arg: f(arg)) for _ in range(5))
            case = f"{label} ∘ {order}, {name}"
            rows.append({"case": case, "compile_s": first - best, "run_s": best})
            print(
                f"{case:36s} compile {first - best:6.2f} s   run {1e3 * best:8.2f} ms", flush=True
            )
    out = {
        "lievi": lievi.__file__,
        "jax": jax.__version__,
        "load_average": os.getloadavg(),
        "timing": "compile: first call less the best of 5; run: best of 5 (jit, final attitude)",
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{options.out}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
