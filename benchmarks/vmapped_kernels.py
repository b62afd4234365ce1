"""Kernel steps under `jax.vmap`: body-steps per second, against the structure-of-arrays path.

A kernel's Newton solve is written for a batch of bodies; `jax.vmap` of a run that steps
bodies by a kernel — `jax.vmap(simulate)` of SE(3) bodies, `simulate_batch` of
`lievi.RigidBodies` systems (each system's run under `jax.vmap`, its bodies stepped by
the kernel) — batches that solve once more. This times, float64, final state only,
`--steps` steps, compile time apart (first call minus the best of the timed calls):

- "SE(3) bodies, simulate_batch": `--batch` free `RigidBodySE3` bodies (random inertia,
  mass, momentum) through the structure-of-arrays kernel, the baseline of the SE(3) rows;
- "SE(3) bodies, vmap(simulate)": the same bodies, `jax.vmap(simulate)` under `jax.jit`;
- "binaries, simulate_batch": `--systems` binary asteroids (`lievi.gravitating_bodies`, as
  `benchmarks/rigid_bodies_throughput.py` builds them), `2·systems` body-steps a step;
  its ratio is against the SE(3) baseline per body-step;

for DEP (exp and Cayley charts) and its fourth-order composition, at `h = --h`: where a
step leaves some bodies above tolerance after the fixed Newton iterations (Cayley at
larger steps, the composition's negative stage) the solve's loop runs, which is what
batching it costs. Interleaved rounds, each figure the best.

    python benchmarks/vmapped_kernels.py [--batch 512] [--systems 256] [--steps 100]
                                         [--h 0.1] [--rounds 3] [--out vmapped_kernels]

Writes `benchmarks/results/<out>.json`. Compare two trees by running the script from
this checkout with `PYTHONPATH=<other tree>` (the imported `lievi` path is saved).
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

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from rigid_bodies_throughput import binaries  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results"
METHODS = {
    "DEP exp": lievi.DEP(),
    "DEP Cayley": lievi.DEP(chart="cayley"),
    "Composition(DEP exp, 4)": lievi.Composition(lievi.DEP(), 4),
}


def se3_bodies(batch, rng):
    inertia = jnp.asarray(rng.uniform(0.5, 2.0, size=(batch, 3)))
    mass = jnp.asarray(rng.uniform(1.0, 3.0, size=batch))
    m0 = jnp.asarray(rng.normal(size=(batch, 6)))
    g0 = jnp.broadcast_to(jnp.eye(4), (batch, 4, 4))
    return inertia, mass, g0, m0


def runners(method, args, rng):
    """The three runs of `method`, each `() -> final m` with the bodies' `(body-steps)`."""
    h, steps = args.h, args.steps
    inertia, mass, g0, m0 = se3_bodies(args.batch, rng)
    bodies = jax.vmap(lievi.RigidBodySE3)(inertia, mass)
    kw = dict(h=h, n_steps=steps, save_every=steps, throw=False)

    def fast():
        return lievi.simulate_batch(bodies, method, g0, m0, system_axis=0, **kw).m[:, -1]

    @jax.jit
    def vmapped(inertia, mass, g0, m0):
        def one(inertia, mass, g0, m0):
            body = lievi.RigidBodySE3(inertia, mass)
            return lievi.simulate(body, method, g0, m0, **kw).m[-1]

        return jax.vmap(one)(inertia, mass, g0, m0)

    systems, bg0, bm0 = binaries(args.systems, rng)

    def binary():
        return lievi.simulate_batch(systems, method, bg0, bm0, system_axis=0, **kw).m[:, -1]

    return {
        "SE(3) bodies, simulate_batch": (fast, args.batch * steps),
        "SE(3) bodies, vmap(simulate)": (
            lambda: vmapped(inertia, mass, g0, m0),
            args.batch * steps,
        ),
        "binaries, simulate_batch": (binary, 2 * args.systems * steps),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--systems", type=int, default=256)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--h", type=float, default=0.1)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--methods", nargs="+", choices=tuple(METHODS), default=tuple(METHODS))
    parser.add_argument("--out", default="vmapped_kernels")
    args = parser.parse_args()
    load = os.getloadavg()
    print(f"lievi from {lievi.__file__}; load {load[0]:.2f}")

    rows = []
    for name in args.methods:
        runs = runners(METHODS[name], args, np.random.default_rng(0))
        first, best = {}, {}
        for label, (run, _) in runs.items():
            start = time.perf_counter()
            jax.block_until_ready(run())
            first[label] = time.perf_counter() - start
        for _ in range(args.rounds):
            for label, (run, _) in runs.items():
                start = time.perf_counter()
                jax.block_until_ready(run())
                seconds = time.perf_counter() - start
                best[label] = min(best.get(label, np.inf), seconds)
        base = runs["SE(3) bodies, simulate_batch"][1] / best["SE(3) bodies, simulate_batch"]
        for label, (_, body_steps) in runs.items():
            rate = body_steps / best[label]
            row = dict(
                method=name,
                run=label,
                seconds=best[label],
                compile_s=max(first[label] - best[label], 0.0),
                body_steps_per_s=rate,
                vs_simulate_batch=rate / base,
            )
            rows.append(row)
            print(
                f"{name:24s} {label:30s} {rate:10.3g} body-steps/s  {rate / base:6.3f}×"
                f"  compile {row['compile_s']:.2f} s"
            )

    out = dict(
        description=__doc__.splitlines()[0],
        lievi=lievi.__file__,
        args=vars(args),
        load_before=load,
        load_after=os.getloadavg(),
        machine=platform.machine(),
        cpus=os.cpu_count(),
        jax=jax.__version__,
        device=str(jax.devices()[0]),
        rows=rows,
    )
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.out}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
