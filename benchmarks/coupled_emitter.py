"""Systems of several bodies on CPU: first call and run time, this checkout against another.

Since this measurement, the eager runs of systems of several bodies (`lievi.RigidBodies`,
`lievi.RigidRotors`) compile with XLA's older loop emitter (`lievi/_compile.py`), as runs
of one or two bodies already did. This times, per case, in a fresh process each (float64,
no persistent compilation cache):

- `first_call_s`: the first call, wall clock (tracing, XLA, the run);
- `run_s`: the best of 4 repeats of the same call after it;

for the checkout `--before` and this one, alternately, `--rounds` times. Cases:

- "64 binaries": `simulate_batch` of 64 binary asteroids, 100 steps of 0.05, every step
  saved: the call of `benchmarks/compile_time.py` (momenta within 10 % of one value);
- "1024 binaries": `simulate_batch` of 1024 random binary asteroids (as
  `benchmarks/rigid_bodies_throughput.py` draws them), the final state only;
- "Lennard-Jones, N bodies": `simulate` of one system of `N` single-site Lennard-Jones
  bodies (all pairs), 10 steps of 0.01, the final state only;
- "1024 rotor triples": `simulate_batch` of 1024 momenta of one `lievi.RigidRotors`
  system of three rotors coupled by their magnetic dipoles (`lievi.DipoleCoupling`), 50
  steps of 0.05, the final state only;
- "one binary": `simulate` of one binary, 10⁴ steps, every 100th saved (a system of two
  bodies: the older emitter before and after, the control).

    python benchmarks/coupled_emitter.py --before TREE [--rounds 2] [--out coupled_emitter]
                                         [--cases "Lennard-Jones" "rotor"]

`--cases`: only the cases whose name contains one of these.

`TREE`: a checkout of the code before (e.g. `git worktree add /tmp/before REV`). Writes
`benchmarks/results/<out>.json`. Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

from first_call import RESULTS, first_and_best, run_in_checkout

SETUP = """
import json, sys, time
sys.path.insert(0, "benchmarks")
import numpy as np
import compile_time  # float64, no persistent compilation cache
from rigid_bodies_throughput import binaries, lennard_jones_cloud
import jax, jax.numpy as jnp, lievi

integrators = compile_time.integrators()
"""

CASES = {
    **{
        f"64 binaries, {name}": f"""
system, g0, m0 = compile_time.binary()
ms = compile_time.batch_momenta(m0, 64)
call = lambda: lievi.simulate_batch(
    system, integrators[{name!r}], g0, ms, h=0.05, n_steps=100, save_every=1
).m
"""
        for name in ("DEP exp", "DEP cayley", "Composition(DEP exp, 4)")
    },
    **{
        f"1024 binaries, {name}, {steps} steps": f"""
system, g0, m0 = binaries(1024, np.random.default_rng(0))
call = lambda: lievi.simulate_batch(
    system, integrators[{name!r}], g0, m0, h=0.05, n_steps={steps}, save=(), throw=False
)
"""
        for name, steps in (
            ("DEP exp", 50),
            ("DEP cayley", 50),
            ("Composition(DEP exp, 4)", 20),
            ("LiePoissonSplitting", 50),
            ("RK4", 50),
        )
    },
    **{
        f"Lennard-Jones, {n} bodies, {name}": f"""
system, g0, m0 = lennard_jones_cloud({n}, np.random.default_rng(0))
call = lambda: lievi.simulate(
    system, integrators[{name!r}], g0, m0, h=0.01, n_steps=10, save_every=10
).m
"""
        for n, name in ((512, "DEP cayley"), (2048, "DEP cayley"), (2048, "LiePoissonSplitting"))
    },
    **{
        f"1024 rotor triples, {name}": f"""
coupling = lievi.DipoleCoupling(
    jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.2, 0.0]]),
    jnp.array([[0.0, 0.0, 1.0], [0.3, 0.0, 0.8], [0.0, 0.5, 0.5]]),
)
system = lievi.RigidRotors(jnp.array([[1.0, 2.0, 3.0], [1.5, 1.0, 2.0], [2.0, 2.5, 1.0]]), coupling)
g0 = jnp.tile(jnp.eye(3), (3, 1, 1))
m0 = jnp.asarray(np.random.default_rng(0).normal(size=(1024, 3, 3)))
call = lambda: lievi.simulate_batch(
    system, integrators[{name!r}], g0, m0, h=0.05, n_steps=50, save=(), throw=False
)
"""
        for name in ("DEP exp", "LiePoissonSplitting")
    },
    "one binary, DEP exp, 1e4 steps": """
system, g0, m0 = compile_time.binary()
call = lambda: lievi.simulate(
    system, integrators["DEP exp"], g0, m0, h=0.05, n_steps=10_000, save_every=100
).m
""",
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", required=True, help="a checkout of the code before")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", default="coupled_emitter")
    parser.add_argument("--cases", nargs="+", default=None)
    args = parser.parse_args()
    cases = {
        name: code
        for name, code in CASES.items()
        if args.cases is None or any(part in name for part in args.cases)
    }
    load = os.getloadavg()
    trees = {"before": args.before, "after": None}
    rows = {case: {tree: {"first_call_s": [], "run_s": []} for tree in trees} for case in cases}
    for round_ in range(args.rounds):
        for tree, path in trees.items():
            print(f"round {round_ + 1}, {tree}:")
            for case, code in cases.items():
                out = json.loads(run_in_checkout(SETUP + code + first_and_best(4), path))
                for key, value in out.items():
                    rows[case][tree][key].append(value)
                print(
                    f"  {case:48s} first call {out['first_call_s']:6.2f} s"
                    f"   run {1e3 * out['run_s']:8.1f} ms",
                    flush=True,
                )
    print("\nbest of the rounds, after/before:")
    for case, row in rows.items():
        first = min(row["after"]["first_call_s"]) / min(row["before"]["first_call_s"])
        run = min(row["after"]["run_s"]) / min(row["before"]["run_s"])
        print(f"  {case:48s} first call {first:5.2f}×   run {run:5.2f}×")
    out = {
        "description": __doc__.splitlines()[0],
        "before": args.before,
        "rounds": args.rounds,
        "load_before": load,
        "load_after": os.getloadavg(),
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "rows": rows,
    }
    path = RESULTS / f"{args.out}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
