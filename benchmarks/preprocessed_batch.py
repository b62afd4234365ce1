"""Per body-step cost of `PreprocessedMoserVeselov(8)` in `simulate_batch`, on its batch
kernel and on the generic path (a subclass: its `init` and step under `jax.vmap`), beside
`MoserVeselov()` and `RKMK8()`; and the start-up, the modified moments per body.

HLW body `(2, 1, 2/3)`, momenta `Π₀ = (cos 1.1, 0, sin 1.1)` scaled per body, `h = 0.1`,
float64, one saved state, under `jax.jit`. CPU time, best of `--repeats`, the methods
alternated in one process. Run pinned to one core: `taskset -c 0 python benchmarks/...`.
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402
from lievi._integrators._preprocessed_dmv import preprocessing  # noqa: E402

try:  # the kernel's per-run constants (absent before the kernel: the generic path only)
    from lievi._integrators._preprocessed_dmv import modified_principal_moments
except ImportError:  # pragma: no cover
    modified_principal_moments = None

INERTIA = jnp.array([2.0, 1.0, 2 / 3])
M0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
H = 0.1


class GenericPreprocessed(lievi.PreprocessedMoserVeselov):
    """The generic path (a subclass has no kernel): the cost before the kernel."""


def best(f, repeats):
    jax.block_until_ready(f())
    times = []
    for _ in range(repeats):
        t = time.process_time()
        jax.block_until_ready(f())
        times.append(time.process_time() - t)
    return min(times)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--batches", type=int, nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    body = lievi.RigidBody(INERTIA)
    methods = {
        "PMV(8) kernel": lievi.PreprocessedMoserVeselov(8),
        "PMV(8) generic": GenericPreprocessed(8),
        "MoserVeselov": lievi.MoserVeselov(),
        "RKMK8": lievi.RKMK8(),
    }
    save = lievi.Save(every=args.steps, stats=False)
    for batch in args.batches:
        scales = 1 + 0.2 * jnp.sin(jnp.arange(batch))
        m0s = M0 * scales[:, None]
        g0s = jnp.broadcast_to(jnp.eye(3), (batch, 3, 3))
        runs = {}
        for name, method in methods.items():

            def run(m, method=method, g0s=g0s):
                return lievi.simulate_batch(
                    body, method, g0s, m, h=H, n_steps=args.steps, save=save, throw=False
                ).m

            runs[name] = jax.jit(run)
        start = {"init (generic)": jax.jit(jax.vmap(lambda m: preprocessing(body, m, H, 8)))}
        if modified_principal_moments is not None:
            start["prepare_run (kernel)"] = jax.jit(
                jax.vmap(lambda m: modified_principal_moments(INERTIA, m, H, 8))
            )
        timings = {name: [] for name in [*runs, *start]}
        for _ in range(args.repeats):  # alternate the methods
            for name, f in runs.items():
                timings[name].append(best(lambda f=f, m=m0s: f(m), 1))
            for name, f in start.items():
                timings[name].append(best(lambda f=f, m=m0s: f(m), 1))
        for name in runs:
            ns = min(timings[name]) / (batch * args.steps) * 1e9
            print(f"batch {batch:5d}  {name:22s} {ns:8.1f} ns per body-step")
        for name in start:
            us = min(timings[name]) / batch * 1e6
            print(f"batch {batch:5d}  {name:22s} {us:8.2f} us per body (start-up)")


if __name__ == "__main__":
    main()
