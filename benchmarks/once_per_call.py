"""The programs an eager call runs once (input checks, set-up, join, result check) under
XLA's older loop emitter against its defaults: their compile time and the calls' run time.

`lievi/_compile.py` compiles those programs (`once_per_call`) with `SMALL_RUN_OPTIONS` on
CPU whatever the run's size. This measures both choices in one process, switching
`lievi._compile.small_run_options_apply`, float64, no persistent compilation cache. Every
case is a batch of single bodies, whose blocks of steps keep XLA's defaults either way:

- compile: for each first-call case, `jax.clear_caches()`, then the call, with one choice
  and then the other, `--rounds` times; the XLA compile time of every program but the
  largest (the block of steps), from JAX's monitoring events;
- run: for each run case, both programs compiled, then the call timed `--repeats` times
  with each choice alternately; the best of each.

    python benchmarks/once_per_call.py [--rounds 2] [--repeats 7] [--out once_per_call]

Writes `benchmarks/results/<out>.json`.
"""

from __future__ import annotations

import argparse
import collections
import pathlib
import sys

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", None)

import jax.numpy as jnp  # noqa: E402

import lievi  # noqa: E402
from lievi import _compile  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import compile_time  # noqa: E402
from first_call import write_results  # noqa: E402

APPLIES = _compile.small_run_options_apply


def first_call_cases():
    """First calls of `simulate_batch` as in `benchmarks/compile_time.py`: 64 bodies, 100
    steps of 0.05, every step saved."""
    systems, integrators = compile_time.systems(), compile_time.integrators()

    def batch(system, integrator):
        body, g0, m0 = systems[system]
        ms = compile_time.batch_momenta(m0, 64)
        method = integrators[integrator]
        return lambda: lievi.simulate_batch(body, method, g0, ms, h=0.05, n_steps=100)

    # Batches of single bodies only: their blocks keep XLA's defaults whichever way
    # `small_run_options_apply` answers (`RunProgram.for_bodies`).
    return {
        f"{system}, {integrator}, simulate_batch (64)": batch(system, integrator)
        for system, integrator in [
            ("RigidBody (free)", "DEP exp"),
            ("GeneralizedRigidBody SO(4)", "DEP exp"),
            ("RigidBodySE3 (free)", "DEP exp"),
            ("RigidBodySE3 (free)", "Composition(DEP exp, 4)"),
            ("RigidBodySE3 (free)", "RKMK8"),
        ]
    }


def run_cases():
    """Calls whose inputs and outputs are large beside their steps: 10⁴ bodies, 100 steps."""
    body = lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))
    se3 = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
    ms = jax.random.normal(jax.random.PRNGKey(0), (10_000, 3))
    ms6 = 0.1 * jax.random.normal(jax.random.PRNGKey(1), (10_000, 6))
    split, dep = lievi.LiePoissonSplitting(), lievi.DEP()
    return {
        "1e4 SO(3) bodies, splitting, every step saved": lambda: lievi.simulate_batch(
            body, split, jnp.eye(3), ms, h=0.05, n_steps=100
        ),
        "1e4 SO(3) bodies, splitting, final state": lambda: lievi.simulate_batch(
            body, split, jnp.eye(3), ms, h=0.05, n_steps=100, save_every=100
        ),
        "1e4 SO(3) bodies, DEP exp, every step saved": lambda: lievi.simulate_batch(
            body, dep, jnp.eye(3), ms, h=0.05, n_steps=100
        ),
        "1e4 SE(3) bodies, DEP exp, every step saved": lambda: lievi.simulate_batch(
            se3, dep, jnp.eye(4), ms6, h=0.05, n_steps=100
        ),
        "1e4 SO(3) bodies, splitting, every step saved, throw=True": lambda: lievi.simulate_batch(
            body, split, jnp.eye(3), ms, h=0.05, n_steps=100, throw=True
        ),
    }


def choose(older: bool) -> None:
    _compile.small_run_options_apply = (lambda: APPLIES()) if older else (lambda: False)


def other_programs_xla(call) -> float:
    """XLA's compile time of every program of `call`'s first call but the largest."""
    times = collections.Counter()

    def listen(event, seconds, fun_name="", **_):
        if event.endswith("backend_compile_duration"):
            times[fun_name] += seconds

    jax.clear_caches()
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        jax.block_until_ready(call())
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return sum(times.values()) - max(times.values())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", default="once_per_call")
    args = parser.parse_args()
    compiles, runs = [], []
    for name, call in first_call_cases().items():
        seconds = {True: [], False: []}
        for _ in range(args.rounds):
            for older in (True, False):
                choose(older)
                seconds[older].append(other_programs_xla(call))
        compiles.append({"case": name, "older_s": seconds[True], "defaults_s": seconds[False]})
        print(
            f"{name:50s} other programs' XLA: older emitter "
            + " ".join(f"{s:.2f}" for s in seconds[True])
            + " s, defaults "
            + " ".join(f"{s:.2f}" for s in seconds[False])
            + " s",
            flush=True,
        )
    for name, call in run_cases().items():
        for older in (True, False):
            choose(older)
            compile_time.timed(call)
        seconds = {True: [], False: []}
        for _ in range(args.repeats):
            for older in (True, False):
                choose(older)
                seconds[older].append(compile_time.timed(call))
        best = {older: min(values) for older, values in seconds.items()}
        runs.append({"case": name, "older_best_s": best[True], "defaults_best_s": best[False]})
        print(
            f"{name:58s} run: older emitter {1e3 * best[True]:7.1f} ms, defaults "
            f"{1e3 * best[False]:7.1f} ms ({best[True] / best[False]:.2f}×)",
            flush=True,
        )
    choose(True)
    document = {"what": __doc__.splitlines()[0], "compile": compiles, "run": runs}
    write_results(args.out, document)


if __name__ == "__main__":
    main()
