"""Cost and memory of reverse-mode gradients through `simulate`, against the number of steps.

For the HLW rigid body (float64, exp-chart DEP, h = 0.01) and N steps, a trajectory loss
(fixed weights on 10 saved states) is differentiated with respect to the inertia, Π₀ and h.
Measured in the same run, for each N:

- forward time (jit of the loss) and gradient time (jit of `value_and_grad`), best of 3
  after a warm-up (compile time apart), with and without `checkpoint=True`;
- their ratio, the acceptance figure (≤ 5 at N = 1e4);
- memory: XLA's own account of the compiled executable, `memory_analysis()`
  (`temp_size_in_bytes`: the scratch the executable allocates, which is where the stored
  residuals of reverse mode live), for the forward and both gradients.

Writes `benchmarks/results/gradients.json` and `benchmarks/results/gradients.png`.

    python benchmarks/gradients.py           # N = 1e3, 3e3, 1e4, 3e4, 1e5 (several minutes)
    python benchmarks/gradients.py --quick   # N = 1e3, 1e4
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
            save_every=n_steps // N_SAVES,
            throw=False,
            checkpoint=checkpoint,
        )
        return jnp.sum(weights_g * sol.g) + jnp.sum(weights_m * sol.m)

    return loss


def best_time(fn, arg, repeats=3):
    jax.block_until_ready(fn(arg))  # warm-up (and compile, if not yet)
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(arg))
        best = min(best, time.perf_counter() - start)
    return best


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
    forward, row["compile_forward_s"], row["temp_bytes_forward"] = compiled(make_loss(n_steps, False), params)
    row["forward_s"] = best_time(forward, params)
    values = {}
    for name, checkpoint in (("plain", False), ("checkpoint", True)):
        grad, row[f"compile_grad_{name}_s"], row[f"temp_bytes_grad_{name}"] = compiled(
            jax.value_and_grad(make_loss(n_steps, checkpoint)), params
        )
        row[f"grad_{name}_s"] = best_time(grad, params)
        row[f"ratio_{name}"] = row[f"grad_{name}_s"] / row["forward_s"]
        values[name] = grad(params)
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
    ax1.semilogx(n, [r["ratio_checkpoint"] for r in rows], "s-", label="gradient / forward, checkpoint=True")
    ax1.axhline(5, color="k", ls="--", lw=1, label="acceptance: 5×")
    ax1.set(xlabel="steps N", ylabel="time ratio", title="Gradient cost relative to the forward pass")
    ax1.set_ylim(bottom=0)
    ax1.legend()
    mib = 2.0**20
    ax2.loglog(n, [r["temp_bytes_grad_plain"] / mib for r in rows], "o-", label="gradient, plain")
    ax2.loglog(n, [r["temp_bytes_grad_checkpoint"] / mib for r in rows], "s-", label="gradient, checkpoint=True")
    ax2.loglog(n, [r["temp_bytes_forward"] / mib for r in rows], "^-", label="forward")
    ref = rows[0]["temp_bytes_grad_checkpoint"] / mib
    ax2.loglog(n, ref * np.sqrt(n / n[0]), "k:", lw=1, label="∝ √N")
    ax2.set(xlabel="steps N", ylabel="MiB (XLA temp allocation)", title="Memory of the compiled executable")
    ax2.legend()
    fig.suptitle("HLW rigid body, exp-chart DEP, float64, " + platform.processor() + f" ({jax.devices()[0].platform})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only N = 1e3 and 1e4")
    args = parser.parse_args()
    sizes = [1_000, 10_000] if args.quick else [1_000, 3_000, 10_000, 30_000, 100_000]
    rows = []
    for n in sizes:
        row = measure(n)
        rows.append(row)
        print(
            f"N = {n:>6d}: forward {row['forward_s'] * 1e3:8.1f} ms | gradient {row['ratio_plain']:.2f}× "
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
        "rows": rows,
    }
    suffix = "_quick" if args.quick else ""
    (RESULTS / f"gradients{suffix}.json").write_text(json.dumps(out, indent=2))
    plot(rows, RESULTS / f"gradients{suffix}.png")
    print(f"wrote {RESULTS / f'gradients{suffix}.json'} and .png")


if __name__ == "__main__":
    main()
