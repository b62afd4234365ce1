"""Compile and run time of `Composition` on the fast path, one body and a batch.

For compositions of order 4, 6 and 8 of the Lie–Poisson splitting and of order 4 and 6
of DEP (exp chart), on the free rigid body `I = (1, 2, 3)`, float64, `h = 0.05`: one body
over 1000 steps (`simulate`) and 10⁴ bodies over 100 steps (`simulate_batch`), each
inside `jax.jit`, the final attitude only. Compile time is the first call less the best
of 5 timed calls; run time is the best of 5. Run it on two trees (e.g. with
`PYTHONPATH=<other checkout>`) one after the other to compare them.

With `--per-stage`, the cost of a composition's step against its stages: the inner method
alone and each composition on the batch (free body and the heavy top `I = (1, 2, 3)`,
`ρ = (0, 0, 0.5)`, in gravity), and `run / (stages × the inner method's run)` per
composition (`over_stages_times_base` in the JSON; 1 is the cost of its stages exactly).

    python benchmarks/composition_stages.py [--per-stage] [--out composition_stages]

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
    parser.add_argument("--per-stage", action="store_true", help="stages against the base")
    options = parser.parse_args()
    if options.per_stage:
        return per_stage(options.out)
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
    write(
        options.out,
        rows,
        "compile: first call less the best of 5; run: best of 5 (jit, final attitude)",
    )


def per_stage(out):
    """`--per-stage`: each composition's batched run over (stages × its inner method's)."""
    moments = jnp.array([1.0, 2.0, 3.0])
    systems = {
        "free body": lievi.RigidBody(moments),
        "heavy top": lievi.heavy_top(moments, 1.0, jnp.array([0.0, 0.0, 0.5]), 1.0),
    }
    momenta = jax.random.normal(jax.random.PRNGKey(0), (65_536, 3))
    rows = []
    for problem, system in systems.items():
        for label, inner, orders in (
            ("splitting", lievi.LiePoissonSplitting(), (4, 6, 8)),
            ("DEP", lievi.DEP(), (4, 6)),
        ):
            base = None
            for order in (None, *orders):
                method = inner if order is None else lievi.Composition(inner, order=order)
                stages = 1 if order is None else len(method.coefficients)

                def many(momenta, method=method, system=system):
                    sol = lievi.simulate_batch(
                        system, method, jnp.eye(3), momenta, h=0.05, n_steps=50
                    )
                    return sol.g[:, -1]

                f = jax.jit(many)
                _timed(lambda f=f: f(momenta))
                best = min(_timed(lambda f=f: f(momenta)) for _ in range(7))
                base = best if order is None else base
                case = f"{problem}, {label}" + ("" if order is None else f" ∘ {order}")
                ratio = best / (stages * base)
                rows.append(
                    {"case": case, "stages": stages, "run_s": best, "over_stages_times_base": ratio}
                )
                print(
                    f"{case:32s} {stages:3d} stages  run {1e3 * best:8.2f} ms  "
                    f"over stages × base {ratio:.2f}",
                    flush=True,
                )
    write(out, rows, "run: best of 7 (jit, 65536 bodies x 50 steps, final attitude)")


def write(name, rows, timing):
    out = {
        "lievi": lievi.__file__,
        "jax": jax.__version__,
        "load_average": os.getloadavg(),
        "timing": timing,
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
