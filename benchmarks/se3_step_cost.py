"""Per-step cost on SE(3) against SO(3), same integrators, same run.

For DEP (exponential and Cayley charts) and RK4 this times `simulate` (final state only,
compile time apart) on
- SO(3): the HLW rigid body (`lievi.RigidBody`, 3 momenta, principal moments: DEP takes
  the structure-of-arrays closed-form step of `lievi._kernels._so3`);
- SO(3) tensor: the same body given a full 3×3 inertia tensor (a rotated frame), which
  DEP solves by the generic path (`jax.jacfwd` Jacobian, `linalg.solve`);
- SE(3): a body with a full 6×6 kinetic tensor (`lievi.RigidBodySE3`, Kirchhoff); DEP
  takes the structure-of-arrays closed-form step of `lievi._kernels._se3` (one body:
  every component a scalar), RK4 the closed forms of `lievi.SE3`;
- SE(3) block-diagonal: `M = diag(I, m 1₃)` with the SO(3) body's principal moments (the
  like-for-like counterpart of "SO(3)"), same closed-form step as "SE(3)";
- SE(3) generic: the same body on a group that supplies only `hat`, `vee`, `log` and
  inherits the generic `MatrixLieGroup` derivations (matrix exponential of the 4×4 hat,
  `dexp` from the exponential of a 12×12 block matrix, `dexpinv` by a linear solve): what
  a hand-written subclass gets.

and reports the time per step for one body (`simulate`), for a vmapped batch
(`jax.vmap(simulate)`), and for the same batch through `lievi.simulate_batch` where the
pair has a structure-of-arrays fast path (`lievi.advanced.has_fast_path`: DEP on "SO(3)", and on
"SE(3)" and "SE(3) block-diagonal" through `lievi/_kernels/_se3.py`), with the ratios
SE(3)/SO(3) of each (and to "SO(3) tensor"). Writes
`benchmarks/results/se3_step_cost.json`, with the load average at the start.

    python benchmarks/se3_step_cost.py [--batch 256] [--steps 2000] [--one-thread] [--out NAME]

`--one-thread` runs XLA on one thread (`--xla_cpu_multi_thread_eigen=false
intra_op_parallelism_threads=1`, set before JAX starts): the figures are then the work per
step, repeatable to a few per cent from run to run, where two threads on two cores add
their synchronisation and whatever else the machine runs (ratios moved by up to 2× between
runs). Pin the process to a core too, e.g. `taskset -c 1 python ...`.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

if "--one-thread" in sys.argv:  # XLA reads its flags once, when JAX starts.
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    )

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402
from lievi._groups._base import MatrixLieGroup  # noqa: E402


class GenericSE3(MatrixLieGroup):
    """SE(3) from `hat`, `vee` and `log` only; everything else generic."""

    @property
    def matrix_dim(self):
        return 4

    @property
    def algebra_dim(self):
        return 6

    def hat(self, x):
        return lievi.SE3.hat(x)

    def vee(self, X):
        return lievi.SE3.vee(X)

    def log(self, g):
        return lievi.SE3.log(g)

    def exp_norm(self, x):
        return lievi.SE3.exp_norm(x)

    @property
    def exp_radius(self):
        return float(np.pi)


class GenericBody(lievi.RigidBodySE3):
    def __init__(self, tensor):
        super().__init__(tensor=tensor)
        self.group = GenericSE3()


def timed(fn, *args, repeats=3):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return first - best, best


def problems():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    tensor = jnp.asarray(A @ A.T / 6 + np.diag([1.0, 1.5, 2.0, 3.0, 4.0, 5.0]))
    Q = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.5]))
    return {
        "SO(3)": (lievi.RigidBody(jnp.array([2.0, 1.0, 2 / 3])), jnp.eye(3), 3),
        "SO(3) tensor": (
            lievi.RigidBody(Q @ jnp.diag(jnp.array([2.0, 1.0, 2 / 3])) @ Q.T),
            jnp.eye(3),
            3,
        ),
        "SE(3)": (lievi.RigidBodySE3(tensor=tensor), jnp.eye(4), 6),
        "SE(3) block-diagonal": (
            lievi.RigidBodySE3(inertia=jnp.array([2.0, 1.0, 2 / 3]), mass=3.0),
            jnp.eye(4),
            6,
        ),
        "SE(3) generic": (GenericBody(tensor), jnp.eye(4), 6),
    }


def measure(body, g0, d, integrator, batch, steps, repeats=3):
    rng = np.random.default_rng(1)
    momenta = jnp.asarray(rng.normal(size=(batch, d)))
    poses = jnp.broadcast_to(g0, (batch,) + g0.shape)

    def final(m0):
        sol = lievi.simulate(
            body,
            integrator,
            g0,
            m0,
            h=0.05,
            n_steps=steps,
            save=lievi.Save(every=steps),
            throw=False,
        )
        return sol.m[-1]

    def final_batch(m0):
        sol = lievi.simulate_batch(
            body,
            integrator,
            poses,
            m0,
            h=0.05,
            n_steps=steps,
            save=lievi.Save(g=False, stats=False, every=steps),
            throw=False,
        )
        return sol.m[:, -1]

    compile_single, run_single = timed(jax.jit(final), momenta[0], repeats=repeats)
    _, run_batch = timed(jax.jit(jax.vmap(final)), momenta, repeats=repeats)
    result = {
        "compile_s": compile_single,
        "single_us_per_step": 1e6 * run_single / steps,
        "batched_us_per_body_step": 1e6 * run_batch / (batch * steps),
        "simulate_batch_us_per_body_step": None,
    }
    if lievi.advanced.has_fast_path(body, integrator):
        _, run_fast = timed(jax.jit(final_batch), momenta, repeats=repeats)
        result["simulate_batch_us_per_body_step"] = 1e6 * run_fast / (batch * steps)
    return result


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument(
        "--one-thread", action="store_true", help="XLA on one thread (see the module doc)"
    )
    parser.add_argument(
        "--out", default="se3_step_cost", help="JSON name under benchmarks/results/"
    )
    args = parser.parse_args()
    load = os.getloadavg()[0]

    integrators = {
        "DEP exp": lievi.DEP(chart="exp"),
        "DEP cayley": lievi.DEP(chart="cayley"),
        "RK4": lievi.RK4(),
    }
    results = {}
    for iname, integrator in integrators.items():
        for gname, (body, g0, d) in problems().items():
            # The generic path is ~100× slower: a tenth of the steps and one repeat.
            slow = gname.endswith("generic")
            steps = max(args.steps // 10, 1) if slow else args.steps
            results[f"{iname} / {gname}"] = measure(
                body, g0, d, integrator, args.batch, steps, repeats=1 if slow else 3
            )
    device = str(jax.devices()[0])
    threads = "one XLA thread" if args.one_thread else "XLA's default threads"
    print(
        f"device: {device}, {threads}, float64, batch {args.batch}, {args.steps} steps, "
        f"final state only, load average at start {load:.1f}"
    )
    print(
        f"{'integrator / group':<30}{'compile [s]':>12}{'1 body [µs/step]':>18}"
        f"{'vmap [µs/body-step]':>21}{'simulate_batch':>16}"
        f"{'ratio to SO(3): 1 / vmap / simulate_batch':>44}"
    )
    for name, r in results.items():
        base = results[name.split(" / ")[0] + " / SO(3)"]
        r["ratio_single_to_so3"] = r["single_us_per_step"] / base["single_us_per_step"]
        r["ratio_batched_to_so3"] = r["batched_us_per_body_step"] / base["batched_us_per_body_step"]
        fast, fast_base = (
            r["simulate_batch_us_per_body_step"],
            base["simulate_batch_us_per_body_step"],
        )
        # simulate_batch against SO(3)'s simulate_batch, and against its vmap (the same
        # structure-of-arrays step, one body at a time under `vmap`).
        r["ratio_simulate_batch_to_so3"] = None if fast is None else fast / fast_base
        r["ratio_simulate_batch_to_so3_vmap"] = (
            None if fast is None else fast / base["batched_us_per_body_step"]
        )
        tensor = results[name.split(" / ")[0] + " / SO(3) tensor"]
        r["ratio_single_to_so3_tensor"] = r["single_us_per_step"] / tensor["single_us_per_step"]
        r["ratio_batched_to_so3_tensor"] = (
            r["batched_us_per_body_step"] / tensor["batched_us_per_body_step"]
        )
        fast_text = "—" if fast is None else f"{fast:.3g}"
        ratio_text = "—" if fast is None else f"{r['ratio_simulate_batch_to_so3']:.2f}"
        print(
            f"{name:<30}{r['compile_s']:>12.2f}{r['single_us_per_step']:>18.3g}"
            f"{r['batched_us_per_body_step']:>21.3g}{fast_text:>16}"
            f"{r['ratio_single_to_so3']:>20.2f} / {r['ratio_batched_to_so3']:.2f} / {ratio_text}"
        )
    out = pathlib.Path(__file__).parent / "results" / f"{args.out}.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "device": device,
                "load_average_at_start": load,
                "one_thread": args.one_thread,
                "batch": args.batch,
                "steps": args.steps,
                "results": results,
            },
            indent=2,
        )
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
