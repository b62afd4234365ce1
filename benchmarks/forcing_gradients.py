"""Cost of the gradient with respect to a whole control sequence, against the forward run.

A rigid body (HLW inertia, float64, exp-chart DEP, h = 0.01) driven by a control sequence
`u` of shape `(N, 3)` (`lievi.Control`, zero-order hold) and by damping `−cΩ`
(`lievi.ForceLaw`, whose end-of-step kick is an implicit solve); the loss is a terminal
attitude and momentum cost plus `Σ h|u_k|²`. Measured in the same run, for each N:

- the forward cost (jit of the loss) and the gradient cost (jit of `value_and_grad` with
  respect to `u` and `c`), with and without `checkpoint=True`, as process CPU time, best
  of 7 interleaved rounds after a warm-up (CPU time: the machine is shared, and time
  slices lost to other processes inflate wall times at random);
- their ratio, the acceptance figure (≤ 5);
- the Newton iterations per step of the forward run.

Writes `benchmarks/results/forcing_gradients.json`.

    python benchmarks/forcing_gradients.py           # N = 500, 2000, 8000
    python benchmarks/forcing_gradients.py --quick   # N = 500, 2000
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
H = 0.01
INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])


def damping(t, g, m, c):
    return -c * m / INERTIA


def make_loss(n_steps: int, checkpoint):
    target = lievi.SO3.exp(jnp.array([0.3, 0.2, -0.4]))
    body = lievi.RigidBody(INERTIA)

    def loss(params):
        sol = lievi.simulate(
            body,
            lievi.DEP(),
            jnp.eye(3),
            jnp.array([np.cos(1.1), 0.0, np.sin(1.1)]),
            h=H,
            n_steps=n_steps,
            save_every=n_steps,
            throw=False,
            checkpoint=checkpoint,
            forcing=(lievi.Control(params["u"]), lievi.ForceLaw(damping)),
            args=params["c"],
        )
        terminal = jnp.sum((sol.g[-1] - target) ** 2) + jnp.sum(sol.m[-1] ** 2)
        return terminal + H * jnp.sum(params["u"] ** 2)

    return loss


def best_times(fns, arg, repeats=7):
    for fn in fns:
        jax.block_until_ready(fn(arg))  # warm-up
    wall = [np.inf] * len(fns)
    cpu = [np.inf] * len(fns)
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            start_wall, start_cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(arg))
            wall[i] = min(wall[i], time.perf_counter() - start_wall)
            cpu[i] = min(cpu[i], time.process_time() - start_cpu)
    return wall, cpu


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    ns = (500, 2000) if parser.parse_args().quick else (500, 2000, 8000)
    rows = []
    for n in ns:
        params = {
            "u": jnp.asarray(0.3 * np.random.default_rng(0).normal(size=(n, 3))),
            "c": jnp.asarray(0.2),
        }
        forward = jax.jit(make_loss(n, False))
        gradient = jax.jit(jax.value_and_grad(make_loss(n, False)))
        gradient_ckpt = jax.jit(jax.value_and_grad(make_loss(n, True)))
        wall, cpu = best_times([forward, gradient, gradient_ckpt], params)
        sol = lievi.simulate(
            lievi.RigidBody(INERTIA),
            lievi.DEP(),
            jnp.eye(3),
            jnp.array([np.cos(1.1), 0.0, np.sin(1.1)]),
            h=H,
            n_steps=n,
            forcing=(lievi.Control(params["u"]), lievi.ForceLaw(damping)),
            args=0.2,
        )
        row = {
            "n_steps": n,
            "forward_cpu_s": cpu[0],
            "gradient_cpu_s": cpu[1],
            "gradient_checkpointed_cpu_s": cpu[2],
            "forward_wall_s": wall[0],
            "gradient_wall_s": wall[1],
            "gradient_checkpointed_wall_s": wall[2],
            "ratio": cpu[1] / cpu[0],
            "ratio_checkpointed": cpu[2] / cpu[0],
            "newton_iterations_per_step": float(sol.stats["total_newton_iterations"]) / n,
        }
        rows.append(row)
        print(
            f"N = {n:6d}: forward {cpu[0] * 1e3:8.2f} ms, gradient {cpu[1] * 1e3:8.2f} ms "
            f"(×{row['ratio']:.2f}), checkpointed {cpu[2] * 1e3:8.2f} ms (×{row['ratio_checkpointed']:.2f})"
        )
    RESULTS.mkdir(exist_ok=True)
    out = {
        "problem": "rigid body I = (2, 1, 2/3), DEP exp chart, h = 0.01, float64; control u (N, 3) "
        "held per step plus damping −cΩ (implicit end kick); gradient w.r.t. u and c",
        "machine": platform.processor() or platform.machine(),
        "jax": jax.__version__,
        "rows": rows,
    }
    (RESULTS / "forcing_gradients.json").write_text(json.dumps(out, indent=2))
    print(f"wrote {RESULTS / 'forcing_gradients.json'}")


if __name__ == "__main__":
    main()
