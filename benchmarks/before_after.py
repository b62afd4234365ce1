"""Forward throughput of `simulate_batch` in memory, this tree against an earlier revision,
in the same run: does a change slow the in-memory path?

The earlier revision's `lievi/` is exported with `git archive` into a temporary
directory; each round times both trees, alternately, each in a fresh process (best of
`--repeats` calls after a warm-up call that compiles). Cases: random free rigid bodies,
`DEP` (exp chart, the fast path), `h = 0.1`, float64, `throw=True` (the default), keeping
the final state only, and keeping every 10th step of `(g, m)`.

With `--se3`, the SE(3) DEP kernels of a free rigid body shared by the batch: DEP (exp,
Cayley) and its order-4 composition, at batches 4096 and 65536 as `--fast-paths`, and one
body through `simulate` (1000 steps, every step saved). `--batches` sets other batch sizes
for both.

`--before-tree DIR` takes the earlier `lievi/` from a directory instead of git (a machine
with a copy of the tree but not its history); `--platform cuda` times on an NVIDIA GPU.

With `--fast-paths`, every fast path of one system shared by the batch instead: the free
rigid body and the heavy top (the problems of `work_precision.py`), each with the
splitting, DEP (exp), `RKMK4`, `RKMK8`, the order-4 composition of the splitting and (free
body) Moser–Veselov, at batches 4096 and 65536, 50 steps of 0.05, keeping the final
attitude; each tree times all of them in one process per round (best of `--repeats`).

    python benchmarks/before_after.py --before REV [--batch 100000] [--steps 100]
                                      [--rounds 3] [--fast-paths | --se3] [--out NAME]
                                      [--batches B ...] [--before-tree DIR]
                                      [--platform cpu|cuda]

Writes `benchmarks/results/<out>.json` (default `before_after`).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"

TIMER = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np
import lievi
batch, steps, save_every, repeats = (int(x) for x in sys.argv[1:5])
rng = np.random.default_rng(0)
bodies = jax.vmap(lievi.RigidBody)(jnp.asarray(rng.uniform(0.5, 2.0, (batch, 3))))
m0 = jnp.asarray(rng.normal(size=(batch, 3)))
g0 = jnp.broadcast_to(jnp.eye(3), (batch, 3, 3))
save = ("g", "m") if save_every < steps else ("m",)
def run():
    sol = lievi.simulate_batch(bodies, lievi.DEP(), g0, m0, h=0.1, n_steps=steps,
                               save_every=save_every, save=save)
    jax.block_until_ready(sol)
run()
times, cpu = [], []
for _ in range(repeats):
    start, start_cpu = time.perf_counter(), time.process_time()
    run()
    times.append(time.perf_counter() - start)
    cpu.append(time.process_time() - start_cpu)
print(json.dumps({"seconds": min(times), "cpu_seconds": min(cpu), "lievi": lievi.__file__}))
"""


# What the timers of `--fast-paths` and `--se3` share: `best_of(run, *args)`, the best of
# `repeats` calls after one that compiles, and `batch_rate`, the body-steps/s of
# `simulate_batch` (`steps` steps of 0.05, momenta within 5 % of `m_mean`, the final `g`).
BEST_OF = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np
import lievi
repeats, steps = int(sys.argv[1]), 50
batches = [int(b) for b in sys.argv[2:]] or [4096, 65536]
def best_of(run, *args):
    jax.block_until_ready(run(*args))
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run(*args))
        best = min(best, time.perf_counter() - start)
    return best
def batch_rate(system, method, g0, m_mean, batch):
    rng = np.random.default_rng(0)
    m0 = jnp.asarray(m_mean * (1 + 0.05 * rng.normal(size=(batch, len(m_mean)))))
    @jax.jit
    def run(m0):
        sol = lievi.simulate_batch(system, method, g0, m0, h=0.05, n_steps=steps,
                                   save=("g",), throw=False)
        return sol.g[:, -1]
    return batch * steps / best_of(run, m0)
"""


FAST_PATHS_TIMER = (
    BEST_OF
    + r"""
moments = jnp.asarray([0.6, 0.8, 1.0])
problems = {
    "free body": (lievi.RigidBody(moments), np.array([1.8, 0.4, -0.9])),
    "heavy top": (lievi.heavy_top(moments, 1.0, jnp.asarray([0.0, 0.0, 0.5]), 1.0),
                  np.array([0.5, 0.3, 1.2])),
}
methods = {
    "splitting": lievi.LiePoissonSplitting(), "DEP exp": lievi.DEP(), "RKMK4": lievi.RKMK4(),
    "RKMK8": lievi.RKMK8(),
    "splitting o 4": lievi.Composition(lievi.LiePoissonSplitting(), order=4),
    "Moser-Veselov": lievi.MoserVeselov(),
}
out = {}
for problem, (system, m_mean) in problems.items():
    for name, method in methods.items():
        if name == "Moser-Veselov" and system.potential is not None:
            continue
        for batch in batches:
            rate = batch_rate(system, method, jnp.eye(3), m_mean, batch)
            out[f"{problem}, {name}, batch {batch}"] = rate
print(json.dumps({"body_steps_per_second": out, "lievi": lievi.__file__}))
"""
)


SE3_TIMER = (
    BEST_OF
    + r"""
system = lievi.RigidBodySE3(jnp.asarray([0.6, 0.8, 1.0]), 2.0)
m_mean = np.array([1.8, 0.4, -0.9, 0.5, -0.3, 0.2])
methods = {"DEP exp": lievi.DEP(), "DEP cayley": lievi.DEP(chart="cayley"),
           "DEP exp o 4": lievi.Composition(lievi.DEP(), order=4)}
out = {}
for name, method in methods.items():
    for batch in batches:
        out[f"SE(3), {name}, batch {batch}"] = batch_rate(system, method, jnp.eye(4), m_mean, batch)
    # One body, eagerly (`simulate`'s blocks), every step saved: 1000 steps.
    def one():
        return lievi.simulate(system, method, jnp.eye(4), jnp.asarray(m_mean), h=0.05,
                              n_steps=1000)
    out[f"SE(3), {name}, one body"] = 1000 / best_of(one)
print(json.dumps({"body_steps_per_second": out, "lievi": lievi.__file__}))
"""
)


def fast_paths(
    path, repeats, timer=FAST_PATHS_TIMER, batches=(), platform="cpu"
) -> dict[str, float]:
    """Body-steps/s of every case of `timer` (default `FAST_PATHS_TIMER`) in the tree at
    `path`, on `platform`."""
    argv = [str(repeats), *(str(b) for b in batches)]
    return _run_timer(path, timer, argv, platform)["body_steps_per_second"]


def _run_timer(path, timer, argv, platform="cpu") -> dict:
    """The last line of `timer`'s output (JSON) when run with the `lievi` of `path`."""
    env = dict(os.environ, PYTHONPATH=str(path), JAX_PLATFORMS=platform)
    done = subprocess.run(
        [sys.executable, "-c", timer, *argv],
        env=env,
        cwd=path,  # `python -c` puts the working directory first on the path
        capture_output=True,
        text=True,
    )
    if done.returncode:
        sys.exit(f"the timer failed in {path}:\n{done.stderr}")
    record = json.loads(done.stdout.strip().splitlines()[-1])
    assert record["lievi"].startswith(str(path)), record  # the tree meant, not another
    return record


def time_tree(path, batch, steps, save_every, repeats) -> tuple[float, float]:
    """`(wall, CPU)` seconds of the best call; on a loaded machine the CPU time (all the
    process's threads) is the steadier measure of the work done."""
    record = _run_timer(path, TIMER, [str(x) for x in (batch, steps, save_every, repeats)])
    return record["seconds"], record["cpu_seconds"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--before", required=True, help="the earlier revision (git)")
    parser.add_argument("--batch", type=int, default=100_000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fast-paths", action="store_true", help="every shared-system fast path")
    parser.add_argument("--se3", action="store_true", help="the SE(3) DEP kernels instead")
    parser.add_argument("--out", default="before_after")
    parser.add_argument(
        "--before-tree",
        type=pathlib.Path,
        help="a directory holding the earlier lievi/ (instead of git)",
    )
    parser.add_argument("--batches", type=int, nargs="+", default=(), help="of --se3, --fast-paths")
    parser.add_argument("--platform", default="cpu", choices=("cpu", "cuda"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as before:
        if args.before_tree is None:
            archive = subprocess.run(
                ["git", "-C", str(ROOT), "archive", args.before, "lievi"],
                capture_output=True,
                check=True,
            ).stdout
            subprocess.run(["tar", "-x", "-C", before], input=archive, check=True)
        trees = {"before": (args.before_tree or pathlib.Path(before)).resolve(), "after": ROOT}
        if args.fast_paths or args.se3:
            return compare_fast_paths(trees, args, SE3_TIMER if args.se3 else FAST_PATHS_TIMER)
        cases = {"final state only": args.steps, "every 10th step of (g, m)": 10}
        times = {case: {tree: [] for tree in trees} for case in cases}
        cpu = {case: {tree: [] for tree in trees} for case in cases}
        for _ in range(args.rounds):
            for case, save_every in cases.items():
                for tree, path in trees.items():
                    seconds, cpu_seconds = time_tree(
                        path, args.batch, args.steps, save_every, args.repeats
                    )
                    times[case][tree].append(seconds)
                    cpu[case][tree].append(cpu_seconds)
                    print(
                        f"{case:28s} {tree:6s} {seconds:.4f} s wall, {cpu_seconds:.4f} s CPU",
                        flush=True,
                    )
    report = {
        **_revisions_and_load(args.before),
        "batch": args.batch,
        "steps": args.steps,
        "cases": {
            case: {
                "best_seconds": {tree: min(t) for tree, t in by_tree.items()},
                "all_seconds": by_tree,
                "after_over_before": min(by_tree["after"]) / min(by_tree["before"]),
                "cpu_seconds": cpu[case],
                "cpu_after_over_before": min(cpu[case]["after"]) / min(cpu[case]["before"]),
            }
            for case, by_tree in times.items()
        },
    }
    print(json.dumps(report["cases"], indent=2))
    print(report["uptime"])
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"{args.out}.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


def _revisions_and_load(before: str) -> dict[str, str]:
    """The report's header: both revisions and the machine's load (`uptime`) at the end."""
    head = ["git", "-C", str(ROOT), "rev-parse", "HEAD"]
    return {
        "before": before,
        "after": subprocess.run(head, capture_output=True, text=True).stdout.strip(),
        "uptime": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
    }


def compare_fast_paths(trees, args, timer) -> None:
    """`--fast-paths` (or `--se3`): both trees, alternately, `--rounds` times; the best of
    each case. Each tree's rates are printed as they come, so that a run stopped by a time
    limit still shows what it measured."""
    best = {tree: {} for tree in trees}
    for _ in range(args.rounds):
        for tree, path in trees.items():
            rates = fast_paths(path, args.repeats, timer, args.batches, args.platform)
            print(f"{tree}: " + json.dumps(rates), flush=True)
            for case, rate in rates.items():
                best[tree][case] = max(best[tree].get(case, 0.0), rate)
    ratios = {case: best["after"][case] / best["before"][case] for case in best["after"]}
    for case, ratio in ratios.items():
        print(f"{case:42s} {best['before'][case]:.3e} -> {best['after'][case]:.3e}  {ratio:.2f}x")
    report = {
        **_revisions_and_load(args.before),
        "rounds": args.rounds,
        "platform": args.platform,
        "body_steps_per_second": best,
        "after_over_before": ratios,
    }
    out = RESULTS / f"{args.out}.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
