"""Cost and memory of reverse-mode gradients through `simulate`, against the number of steps.

For the HLW rigid body (float64, exp-chart DEP, h = 0.01) and N steps, a trajectory loss
(fixed weights on 10 saved states) is differentiated with respect to the inertia, Π₀ and h.
Measured in the same run, for each N:

- forward cost (jit of the loss) and gradient cost (jit of `value_and_grad`), with and
  without `checkpoint=True`, as process CPU time (wall time recorded too): best of 7
  rounds, the three measured in turn in each round, after a warm-up, compile time apart.
  CPU time, because the machine this was written on is shared and loaded: time slices
  lost to other processes inflate wall times at random, not the CPU time of this one;
- their ratio, the acceptance figure (≤ 5 at N = 1e4);
- memory: XLA's own account of the compiled executable, `memory_analysis()`
  (`temp_size_in_bytes`: the scratch the executable allocates, which is where the stored
  residuals of reverse mode live), for the forward and both gradients.

Writes `benchmarks/results/gradients.json` and `benchmarks/results/gradients.png`.

    python benchmarks/gradients.py           # N = 1e3, 3e3, 1e4, 3e4, 1e5 (several minutes)
    python benchmarks/gradients.py --quick   # N = 1e3, 1e4

`--batch` measures instead batched gradients through `simulate_batch`'s fast path: random
bodies (`benchmarks/throughput.py`'s), batch 1e5, 100 steps of h = 0.1, float64, a loss of
the final state (fixed random weights on g and Π, summed over the bodies) differentiated
with respect to every body's inertia, Π₀ and h. For every fast method: the forward cost,
the cost of `value_and_grad` without and with `checkpoint=True`, their ratios (the
acceptance figure: ≤ 5), and for reference the `fast=False` gradient (`jax.vmap(simulate)`)
on a 10× smaller batch, as body-steps per second. Writes `gradients_batch.json`.

    python benchmarks/gradients.py --batch [--bodies 100000] [--steps 100]

`--forcing` measures the gradient with respect to a whole control sequence against the
forward run (N = 500, 2000, 8000; `--quick`: 500, 2000); writes `forcing_gradients.json`.

    python benchmarks/gradients.py --forcing [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
H = 0.01
N_SAVES = 10


def make_loss(n_steps: int, checkpoint):
    weights_g = jnp.asarray(np.random.default_rng(0).normal(size=(N_SAVES + 1, 3, 3)))
    weights_m = jnp.asarray(np.random.default_rng(1).normal(size=(N_SAVES + 1, 3)))

    def loss(params):
        sol = lievi.simulate(
            lievi.RigidBody(params["inertia"]),
            lievi.DEP(),
            jnp.eye(3),
            params["m0"],
            h=params["h"],
            n_steps=n_steps,
            save=lievi.Save(every=n_steps // N_SAVES),
            throw=False,
            checkpoint=checkpoint,
        )
        return jnp.sum(weights_g * sol.g) + jnp.sum(weights_m * sol.m)

    return loss


def best_times(fns, arg, repeats=7):
    """Best wall and CPU time of each function, measured in interleaved rounds so that load
    from other processes on a shared machine hits every function alike. The cost ratios use
    the process CPU time (`time.process_time`), which time slices lost to other processes do
    not inflate; the wall times are recorded too."""
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


def compiled(fn, arg):
    start = time.perf_counter()
    exe = jax.jit(fn).lower(arg).compile()
    seconds = time.perf_counter() - start
    return exe, seconds, exe.memory_analysis().temp_size_in_bytes


def measure(n_steps: int):
    params = {
        "inertia": jnp.array([2.0, 1.0, 2.0 / 3.0]),
        "m0": jnp.array([np.cos(1.1), 0.0, np.sin(1.1)]),
        "h": jnp.asarray(H),
    }
    row = {"n_steps": n_steps}
    forward, row["compile_forward_s"], row["temp_bytes_forward"] = compiled(
        make_loss(n_steps, False), params
    )
    grads = {}
    for name, checkpoint in (("plain", False), ("checkpoint", True)):
        grads[name], row[f"compile_grad_{name}_s"], row[f"temp_bytes_grad_{name}"] = compiled(
            jax.value_and_grad(make_loss(n_steps, checkpoint)), params
        )
    wall, cpu = best_times([forward, grads["plain"], grads["checkpoint"]], params)
    row["forward_s"], row["grad_plain_s"], row["grad_checkpoint_s"] = cpu
    row["forward_wall_s"], row["grad_plain_wall_s"], row["grad_checkpoint_wall_s"] = wall
    values = {}
    for name in grads:
        row[f"ratio_{name}"] = row[f"grad_{name}_s"] / row["forward_s"]
        row[f"ratio_{name}_wall"] = row[f"grad_{name}_wall_s"] / row["forward_wall_s"]
        values[name] = grads[name](params)
    # Same numbers either way (the test suite checks this too).
    row["checkpoint_grad_max_rel_diff"] = float(
        max(
            jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b))
            for a, b in zip(jax.tree.leaves(values["checkpoint"]), jax.tree.leaves(values["plain"]))
        )
    )
    return row


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.array([r["n_steps"] for r in rows])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax1.semilogx(n, [r["ratio_plain"] for r in rows], "o-", label="gradient / forward, plain")
    ax1.semilogx(
        n, [r["ratio_checkpoint"] for r in rows], "s-", label="gradient / forward, checkpoint=True"
    )
    ax1.axhline(5, color="k", ls="--", lw=1, label="acceptance: 5×")
    ax1.set(
        xlabel="steps N", ylabel="time ratio", title="Gradient cost relative to the forward pass"
    )
    ax1.set_ylim(bottom=0)
    ax1.legend()
    mib = 2.0**20
    ax2.loglog(n, [r["temp_bytes_grad_plain"] / mib for r in rows], "o-", label="gradient, plain")
    ax2.loglog(
        n,
        [r["temp_bytes_grad_checkpoint"] / mib for r in rows],
        "s-",
        label="gradient, checkpoint=True",
    )
    ax2.loglog(n, [r["temp_bytes_forward"] / mib for r in rows], "^-", label="forward")
    ref = rows[0]["temp_bytes_grad_checkpoint"] / mib
    ax2.loglog(n, ref * np.sqrt(n / n[0]), "k:", lw=1, label="∝ √N")
    ax2.set(
        xlabel="steps N",
        ylabel="MiB (XLA temp allocation)",
        title="Memory of the compiled executable",
    )
    ax2.legend()
    fig.suptitle(
        "HLW rigid body, exp-chart DEP, float64, "
        + platform.processor()
        + f" ({jax.devices()[0].platform})"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)


BATCH_METHODS = {
    "DEP exp": lambda: lievi.DEP(chart="exp"),
    "DEP cayley": lambda: lievi.DEP(chart="cayley"),
    "Moser-Veselov": lambda: lievi.MoserVeselov(),
    "splitting": lambda: lievi.LiePoissonSplitting(),
    "RK4": lambda: lievi.RK4(),
    "RKMK4": lambda: lievi.RKMK4(),
    "splitting ∘ 4": lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=4),
}


def batch_loss(integrator, steps: int, fast: bool, checkpoint):
    def loss(params, g0, weights):
        sol = lievi.simulate_batch(
            jax.vmap(lievi.RigidBody)(params["inertia"]),
            integrator,
            g0,
            params["m0"],
            h=params["h"],
            n_steps=steps,
            system_axis=0,
            save=lievi.Save(stats=False, every=steps),
            tuning=lievi.advanced.Tuning(fast=fast),
            throw=False,
            checkpoint=checkpoint,
        )
        return jnp.sum(weights[0] * sol.g[:, -1]) + jnp.sum(weights[1] * sol.m[:, -1])

    return loss


def batch_inputs(bodies: int):
    sys_path = str(pathlib.Path(__file__).parent)
    if sys_path not in sys.path:
        sys.path.insert(0, sys_path)
    from throughput import H as step
    from throughput import rigid_body_inputs

    inertia, g0, m0 = rigid_body_inputs(bodies, jnp.float64)
    rng = np.random.default_rng(7)
    weights = (
        jnp.asarray(rng.normal(size=(bodies, 3, 3))),
        jnp.asarray(rng.normal(size=(bodies, 3))),
    )
    params = {"inertia": inertia, "m0": m0, "h": jnp.full((bodies,), step)}
    return params, g0, weights


def measure_batch(name: str, bodies: int, steps: int, repeats: int = 3):
    integrator = BATCH_METHODS[name]()
    params, g0, weights = batch_inputs(bodies)
    args = (params, g0, weights)
    fns = {
        "forward": jax.jit(batch_loss(integrator, steps, True, False)),
        "grad": jax.jit(jax.value_and_grad(batch_loss(integrator, steps, True, False))),
        "grad_checkpoint": jax.jit(jax.value_and_grad(batch_loss(integrator, steps, True, True))),
    }
    row = {"method": name, "bodies": bodies, "steps": steps}
    for key, fn in fns.items():
        start = time.perf_counter()
        exe = fn.lower(*args).compile()
        row[f"compile_{key}_s"] = time.perf_counter() - start
        row[f"temp_bytes_{key}"] = exe.memory_analysis().temp_size_in_bytes
        fns[key] = exe
    wall = {k: np.inf for k in fns}
    cpu = {k: np.inf for k in fns}
    for k, fn in fns.items():
        jax.block_until_ready(fn(*args))  # warm-up
    for _ in range(repeats):
        for k, fn in fns.items():
            start_wall, start_cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(*args))
            wall[k] = min(wall[k], time.perf_counter() - start_wall)
            cpu[k] = min(cpu[k], time.process_time() - start_cpu)
    for k in fns:
        row[f"{k}_cpu_s"], row[f"{k}_wall_s"] = cpu[k], wall[k]
        row[f"{k}_body_steps_per_s_wall"] = bodies * steps / wall[k]
    # On a CPU the ratios use process CPU time (a shared machine's lost time slices inflate
    # wall times at random); on an accelerator the host's CPU time says nothing: wall time.
    clock = cpu if jax.devices()[0].platform == "cpu" else wall
    row["ratio_clock"] = "cpu" if clock is cpu else "wall"
    row["ratio_grad"] = clock["grad"] / clock["forward"]
    row["ratio_grad_checkpoint"] = clock["grad_checkpoint"] / clock["forward"]
    row["ratio_grad_wall"] = wall["grad"] / wall["forward"]
    # The generic gradient (jax.vmap(simulate)) on a 10× smaller batch, and the agreement.
    small = max(bodies // 10, 1)
    small_args = jax.tree.map(lambda x: x[:small], args)
    generic = jax.jit(jax.value_and_grad(batch_loss(integrator, steps, False, False)))
    fast_small = jax.jit(jax.value_and_grad(batch_loss(integrator, steps, True, False)))
    reference = jax.block_until_ready(generic(*small_args))
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    jax.block_until_ready(generic(*small_args))
    row["generic_grad_bodies"] = small
    row["generic_grad_wall_s"] = time.perf_counter() - start_wall
    row["generic_grad_cpu_s"] = time.process_time() - start_cpu
    row["generic_grad_body_steps_per_s_wall"] = small * steps / row["generic_grad_wall_s"]
    mine = fast_small(*small_args)
    row["grad_max_rel_diff_vs_generic"] = float(
        max(
            jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b))
            for a, b in zip(jax.tree.leaves(mine[1]), jax.tree.leaves(reference[1]))
        )
    )
    return row


def main_batch(args):
    load_before = os.getloadavg()
    rows = []
    names = args.methods or list(BATCH_METHODS)
    print(
        f"batched gradients through the fast path: {args.bodies} bodies, {args.steps} steps, float64; "
        f"load average {load_before}"
    )
    print(
        f"{'method':<15}{'forward':>12}{'grad':>12}{'grad/fwd':>10}{'ckpt/fwd':>10}{'fwd bs/s':>11}{'grad bs/s':>11}"
        f"{'generic grad bs/s':>19}{'rel diff':>10}"
    )
    results = pathlib.Path(args.outdir)
    out_path = results / f"{args.out}.json"
    for name in names:
        row = measure_batch(name, args.bodies, args.steps)
        rows.append(row)
        print(
            f"{name:<15}{row['forward_cpu_s']:>10.3f} s{row['grad_cpu_s']:>10.3f} s{row['ratio_grad']:>10.2f}"
            f"{row['ratio_grad_checkpoint']:>10.2f}{row['forward_body_steps_per_s_wall']:>11.3g}"
            f"{row['grad_body_steps_per_s_wall']:>11.3g}{row['generic_grad_body_steps_per_s_wall']:>19.3g}"
            f"{row['grad_max_rel_diff_vs_generic']:>10.1e}",
            flush=True,
        )
        results.mkdir(parents=True, exist_ok=True)
        out = {
            "device": str(jax.devices()[0]),
            "jax": jax.__version__,
            "command": "python benchmarks/gradients.py " + " ".join(sys.argv[1:]),
            "timing": "process CPU time (*_cpu_s) and wall time (*_wall_s): best of 3 interleaved rounds after a warm-up, compile apart; the ratios use ratio_clock (CPU time on a CPU, wall time on an accelerator)",
            "cpu_count": os.cpu_count(),
            "load_average_before": load_before,
            "load_average_after": os.getloadavg(),
            "rows": rows,
        }
        out_path.write_text(json.dumps(out, indent=2))
    print(f"load average before {load_before}, after {os.getloadavg()}; wrote {out_path}")


# ---- --forcing: the gradient with respect to a whole control sequence ---------------------
#
# A rigid body (HLW inertia, float64, exp-chart DEP, h = 0.01) driven by a control sequence
# `u` of shape `(N, 3)` (`lievi.Control`, zero-order hold) and by damping `−cΩ`
# (`lievi.ForceLaw`, whose end-of-step kick is an implicit solve); the loss is a terminal
# attitude and momentum cost plus `Σ h|u_k|²`. For each N: forward and gradient (with
# respect to `u` and `c`, with and without `checkpoint=True`) as process CPU time, their
# ratio (the acceptance figure: ≤ 5), and the Newton iterations per step of the forward
# run. Writes `benchmarks/results/forcing_gradients.json`.

FORCING_H = 0.01
HLW_INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])


def damping(t, g, m, c):
    return -c * m / HLW_INERTIA


def forcing_loss(n_steps: int, checkpoint):
    target = lievi.SO3.exp(jnp.array([0.3, 0.2, -0.4]))
    body = lievi.RigidBody(HLW_INERTIA)

    def loss(params):
        sol = lievi.simulate(
            body,
            lievi.DEP(),
            jnp.eye(3),
            jnp.array([np.cos(1.1), 0.0, np.sin(1.1)]),
            h=FORCING_H,
            n_steps=n_steps,
            save=lievi.Save(every=n_steps),
            throw=False,
            checkpoint=checkpoint,
            forcing=(lievi.Control(params["u"]), lievi.ForceLaw(damping)),
            args=params["c"],
        )
        terminal = jnp.sum((sol.g[-1] - target) ** 2) + jnp.sum(sol.m[-1] ** 2)
        return terminal + FORCING_H * jnp.sum(params["u"] ** 2)

    return loss


def main_forcing(quick: bool):
    ns = (500, 2000) if quick else (500, 2000, 8000)
    rows = []
    for n in ns:
        params = {
            "u": jnp.asarray(0.3 * np.random.default_rng(0).normal(size=(n, 3))),
            "c": jnp.asarray(0.2),
        }
        forward = jax.jit(forcing_loss(n, False))
        gradient = jax.jit(jax.value_and_grad(forcing_loss(n, False)))
        gradient_ckpt = jax.jit(jax.value_and_grad(forcing_loss(n, True)))
        wall, cpu = best_times([forward, gradient, gradient_ckpt], params)
        sol = lievi.simulate(
            lievi.RigidBody(HLW_INERTIA),
            lievi.DEP(),
            jnp.eye(3),
            jnp.array([np.cos(1.1), 0.0, np.sin(1.1)]),
            h=FORCING_H,
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


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only N = 1e3 and 1e4")
    parser.add_argument(
        "--batch", action="store_true", help="batched gradients through the fast path"
    )
    parser.add_argument("--bodies", type=int, default=100_000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--methods", nargs="+", default=None, choices=list(BATCH_METHODS))
    parser.add_argument("--outdir", default=str(RESULTS), help="where --batch writes its JSON")
    parser.add_argument("--out", default="gradients_batch", help="basename of --batch's JSON")
    parser.add_argument(
        "--forcing", action="store_true", help="gradient w.r.t. a control sequence (N = 500…8000)"
    )
    args = parser.parse_args()
    if args.batch:
        return main_batch(args)
    if args.forcing:
        return main_forcing(args.quick)
    sizes = [1_000, 10_000] if args.quick else [1_000, 3_000, 10_000, 30_000, 100_000]
    load_before = os.getloadavg()  # a shared machine: other processes inflate both times
    rows = []
    for n in sizes:
        row = measure(n)
        rows.append(row)
        print(
            f"N = {n:>6d}: forward {row['forward_s'] * 1e3:8.1f} ms CPU | gradient {row['ratio_plain']:.2f}× "
            f"(checkpoint {row['ratio_checkpoint']:.2f}×) | temp memory: forward "
            f"{row['temp_bytes_forward'] / 2**20:7.2f} MiB, gradient {row['temp_bytes_grad_plain'] / 2**20:8.2f} MiB, "
            f"checkpointed {row['temp_bytes_grad_checkpoint'] / 2**20:7.2f} MiB",
            flush=True,
        )
    if len(rows) > 1:
        n = np.log([r["n_steps"] for r in rows])
        for name in ("plain", "checkpoint"):
            slope = np.polyfit(n, np.log([r[f"temp_bytes_grad_{name}"] for r in rows]), 1)[0]
            print(f"memory growth exponent (log-log slope), {name}: {slope:.2f}")
    RESULTS.mkdir(exist_ok=True)
    out = {
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "quick": args.quick,
        "memory_source": "compiled executable memory_analysis().temp_size_in_bytes",
        "timing": "process CPU time (wall time in *_wall_s): best of 7 interleaved rounds after a warm-up, compile excluded",
        "cpu_count": os.cpu_count(),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "rows": rows,
    }
    suffix = "_quick" if args.quick else ""
    (RESULTS / f"gradients{suffix}.json").write_text(json.dumps(out, indent=2))
    plot(rows, RESULTS / f"gradients{suffix}.png")
    print(f"load average before {load_before}, after {os.getloadavg()} ({os.cpu_count()} CPUs)")
    print(f"wrote {RESULTS / f'gradients{suffix}.json'} and .png")


if __name__ == "__main__":
    main()
