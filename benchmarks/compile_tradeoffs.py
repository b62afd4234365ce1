"""What bringing the slowest first compiles under 3 s would cost at run time, per XLA flag set.

The first calls of `benchmarks/compile_time.py` that still compile for more than 3 s on the
2-core reference machine are batches (`simulate_batch` of 64 systems, 100 steps of 0.05,
every step saved, momenta within 10 % of one value: the same call as there) of free SE(3)
bodies and of binary asteroids (`lievi.RigidBodies` on SE(3)²). XLA's own options
trade compile time against run time; this script measures that trade for each of those
calls, each flag set in fresh processes (XLA reads `XLA_FLAGS` once per process),
alternately, round after round:

- `first_call_s`: the first call, wall clock (tracing, XLA, the run);
- `run_s`: the best of 5 repeats of the same call after it.

The flag sets: the default (`XLA_FLAGS` unset), `--xla_cpu_use_fusion_emitters=false`
(XLA's older loop emitter, which lievi already uses for runs of one or two bodies:
docs/compile-times.md), `--xla_backend_optimization_level=0` (LLVM without optimisation),
and both; or those given.

    python benchmarks/compile_tradeoffs.py [--rounds 2] [--flags "" "--xla_cpu_use_fusion_emitters=false"]
                                           [--out compile_tradeoffs]

Writes `benchmarks/results/<out>.json`. Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys

from first_call import RESULTS, first_and_best, run_in_checkout

FLAG_SETS = (
    "",
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_backend_optimization_level=0",
    "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0",
)

# (system, integrator) of `benchmarks/compile_time.py`, batched as there.
CASES = (
    ("RigidBodySE3 (free)", "DEP exp"),
    ("RigidBodySE3 (free)", "Composition(DEP exp, 4)"),
    ("RigidBodySE3 (free)", "RKMK8"),
    ("RigidBodies (binary)", "DEP exp"),
    ("RigidBodies (binary)", "DEP cayley"),
    ("RigidBodies (binary)", "Composition(DEP exp, 4)"),
)

CODE = """
import json, sys, time
sys.path.insert(0, "benchmarks")
import compile_time  # float64, no persistent compilation cache
import jax, lievi

system, g0, m0 = compile_time.systems()[{system!r}]
integrator = compile_time.integrators()[{integrator!r}]
ms = compile_time.batch_momenta(m0, 64)
jax.block_until_ready(ms)
call = lambda: lievi.simulate_batch(
    system, integrator, g0, ms, h=0.05, n_steps=100, save_every=1
).m
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--flags", nargs="+", default=list(FLAG_SETS))
    parser.add_argument("--out", default="compile_tradeoffs")
    args = parser.parse_args()
    load = os.getloadavg()
    rows = {
        flags: {f"{s}, {i}": {"first_call_s": [], "run_s": []} for s, i in CASES}
        for flags in args.flags
    }
    for round_ in range(args.rounds):
        for flags in args.flags:
            print(f"round {round_ + 1}, {flags or '(default)'}:")
            for system, integrator in CASES:
                code = CODE.format(system=system, integrator=integrator) + first_and_best(5)
                out = json.loads(run_in_checkout(code, xla_flags=flags))
                row = rows[flags][f"{system}, {integrator}"]
                for key, value in out.items():
                    row[key].append(value)
                print(
                    f"  {system:22s} {integrator:25s} first call {out['first_call_s']:6.2f} s"
                    f"   run {1e3 * out['run_s']:7.1f} ms"
                )
    document = {
        "description": __doc__.splitlines()[0],
        "command": "python benchmarks/compile_tradeoffs.py " + " ".join(sys.argv[1:]),
        "batch": 64,
        "steps": 100,
        "dtype": "float64",
        "rows": rows,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_before": load,
        "load_after": os.getloadavg(),
    }
    path = RESULTS / f"{args.out}.json"
    path.write_text(json.dumps(document, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
