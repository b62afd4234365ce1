"""`RKMK4` on SE(3): the structure-of-arrays kernel (`RKMK4SE3Kernel`) against the generic
step it replaces (`RKMK4.step` under `jax.vmap`, what `simulate_batch` ran before the
kernel; here through `reference_path()`, which turns every kernel off), in one run.

Random Kirchhoff bodies (a full SPD 6×6 tensor per body) and momenta, free or in uniform
gravity with the centre of mass off the origin, `--steps` steps of 0.05, final state only,
float64. Each path is compiled, then timed `--rounds` times in alternation with the other
(each switch recompiles: the kernel switch is read at trace time); the best of each is
reported, in body-steps per second, with their ratio and the load average.

    python benchmarks/rkmk4_se3_throughput.py [--batch 10000] [--steps 100] [--rounds 3]

Writes `benchmarks/results/rkmk4_se3_throughput.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import lievi  # noqa: E402
from lievi._kernels._base import reference_path  # noqa: E402


def problem(batch, gravity, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(batch, 6, 6))
    tensors = A @ np.swapaxes(A, -1, -2) / 6 + np.diag([1.0, 1.5, 2.0, 2.0, 2.5, 3.0])
    potential = lievi.UniformGravitySE3(2.0, 1.0, jnp.array([0.1, -0.2, 0.3])) if gravity else None
    systems = jax.vmap(lambda M: lievi.RigidBodySE3(tensor=M, potential=potential))(
        jnp.asarray(tensors)
    )
    m0 = jnp.asarray(rng.normal(size=(batch, 6)))
    return systems, m0


def timed_run(systems, m0, steps, rounds):
    """Best wall time of `rounds` runs (after one compiling run) and the final momenta."""

    # The systems an argument, not a constant of the program (XLA would fold them).
    @jax.jit
    def run(systems, m0):
        sol = lievi.simulate_batch(
            systems, lievi.RKMK4(), jnp.eye(4), m0, h=0.05, n_steps=steps, system_axis=0,
            save=("g", "m"), throw=False,
        )  # fmt: skip
        return sol.m[:, -1], sol.result

    jax.block_until_ready(run(systems, m0))
    best = np.inf
    for _ in range(rounds):
        start = time.perf_counter()
        out = jax.block_until_ready(run(systems, m0))
        best = min(best, time.perf_counter() - start)
    return best, out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--outdir", default=str(pathlib.Path(__file__).parent / "results"))
    args = parser.parse_args()
    load = os.getloadavg()[0]
    results = {}
    for gravity in (False, True):
        name = "gravity" if gravity else "free"
        systems, m0 = problem(args.batch, gravity)
        kind = type(lievi.RKMK4().batch_kernel(systems, batched=True)).__name__
        kernel, generic = np.inf, np.inf
        for _ in range(2):  # alternate: kernel, generic, kernel, generic
            seconds, (m_fast, result) = timed_run(systems, m0, args.steps, args.rounds)
            kernel = min(kernel, seconds)
            with reference_path():
                seconds, (m_generic, _) = timed_run(systems, m0, args.steps, args.rounds)
            generic = min(generic, seconds)
        body_steps = args.batch * args.steps
        difference = float(jnp.max(jnp.abs(m_fast - m_generic)) / jnp.max(jnp.abs(m_generic)))
        results[name] = dict(
            kernel=kind,
            kernel_body_steps_per_s=body_steps / kernel,
            generic_body_steps_per_s=body_steps / generic,
            speedup=generic / kernel,
            all_successful=bool(np.all(np.asarray(result) == 0)),
            max_relative_difference_m=difference,
        )
        print(
            f"{name:>8}: kernel ({kind}) {body_steps / kernel:.3g} body-steps/s, generic "
            f"{body_steps / generic:.3g}, {generic / kernel:.1f}× (final m differ by "
            f"{difference:.1e})"
        )
    meta = dict(
        batch=args.batch, steps=args.steps, rounds=args.rounds, cpu_count=os.cpu_count(),
        load_average_at_start=load, load_average_at_end=os.getloadavg()[0],
        device=str(jax.devices()[0]),
    )  # fmt: skip
    outdir = pathlib.Path(args.outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    path = outdir / "rkmk4_se3_throughput.json"
    path.write_text(json.dumps({"meta": meta, **results}, indent=1))
    print(f"wrote {path} (load average {load:.1f} at the start)")


if __name__ == "__main__":
    main()
