"""Where a first call's time goes: XLA compiling the run's program, the other programs, and
the rest (tracing, lowering, the run, Python).

For the calls of `benchmarks/compile_time.py` whose first compile is the longest (its
SE(3) rows: 64 free `RigidBodySE3` bodies or 64 binary asteroids on SE(3)², 100 steps of
0.05, every step saved, and one binary), each in a fresh process (float64, no persistent
compilation cache), this times the first call by wall clock and splits it with JAX's
monitoring events (`/jax/core/compile/*_duration`, each with its program's name):

- `largest_xla_s`: XLA compiling the largest program (the block of steps, `_block`);
- `largest_trace_lower_s`: tracing and lowering that program;
- `other_xla_s`, `other_programs`: XLA compiling every other program of the call (input
  checks, the set-up, the join of the blocks, the result check);
- `rest_s`: everything else (tracing and lowering the other programs, running, Python).

    python benchmarks/first_call_breakdown.py [--rounds 2] [--tree PATH] [--out first_call_breakdown]

`--tree PATH` times another checkout (`first_call.run_in_checkout`). Writes
`benchmarks/results/<out>.json`. The machine's speed moves all of these together; the
shares are what compare across runs.
"""

from __future__ import annotations

import argparse
import json

from first_call import run_in_checkout, write_results

SETUP = """
import collections, json, sys, time
sys.path.insert(0, "benchmarks")
import compile_time  # float64, no persistent compilation cache
import jax, lievi

events = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, fun_name="", **_: events.append((event, fun_name, seconds))
)
"""

TIMED = """
system, g0, m0 = compile_time.systems()[{system!r}]
integrator = compile_time.integrators()[{integrator!r}]
ms = compile_time.batch_momenta(m0, 64)
jax.block_until_ready(ms)
if {batch}:
    call = lambda: lievi.simulate_batch(system, integrator, g0, ms, h=0.05, n_steps=100)
else:
    call = lambda: lievi.simulate(system, integrator, g0, m0, h=0.05, n_steps=100)
del events[:]
start = time.perf_counter()
jax.block_until_ready(call())
wall = time.perf_counter() - start
xla = collections.Counter()
for event, name, seconds in events:
    if event.endswith("backend_compile_duration"):
        xla[name] += seconds
largest, largest_xla = xla.most_common(1)[0]
# Trace events name the function (`_block`), lowering and compile events the program
# (`jit(_block)`).
trace_lower = sum(
    seconds
    for event, name, seconds in events
    if name in (largest, largest[4:-1])
    and event.endswith(("jaxpr_trace_duration", "jaxpr_to_mlir_module_duration"))
)
other = sum(xla.values()) - largest_xla
print(json.dumps({{
    "first_call_s": wall,
    "largest": largest,
    "largest_xla_s": largest_xla,
    "largest_trace_lower_s": trace_lower,
    "other_xla_s": other,
    "other_programs": len(xla) - 1,
    "rest_s": wall - largest_xla - trace_lower - other,
}}))
"""

# The rows of `benchmarks/compile_time.py` over 3 s: `(system, integrator, batch)`.
CASES = [
    ("RigidBodySE3 (free)", "DEP exp", True),
    ("RigidBodySE3 (free)", "Composition(DEP exp, 4)", True),
    ("RigidBodySE3 (free)", "RKMK8", True),
    ("RigidBodies (binary)", "DEP exp", False),
    ("RigidBodies (binary)", "Composition(DEP exp, 4)", False),
    ("RigidBodies (binary)", "DEP exp", True),
    ("RigidBodies (binary)", "DEP cayley", True),
    ("RigidBodies (binary)", "Composition(DEP exp, 4)", True),
]

KEYS = ("first_call_s", "largest_xla_s", "largest_trace_lower_s", "other_xla_s", "rest_s")


def breakdown(system: str, integrator: str, batch: bool, tree: str | None = None) -> dict:
    code = SETUP + TIMED.format(system=system, integrator=integrator, batch=batch)
    return json.loads(run_in_checkout(code, tree))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--tree", default=None, help="another checkout of lievi to time")
    parser.add_argument("--out", default="first_call_breakdown")
    args = parser.parse_args()
    rows = []
    for system, integrator, batch in CASES:
        runs = [breakdown(system, integrator, batch, args.tree) for _ in range(args.rounds)]
        call = "simulate_batch (64)" if batch else "simulate"
        row = {"system": system, "integrator": integrator, "call": call, "runs": runs}
        rows.append(row)
        best = min(runs, key=lambda run: run["first_call_s"])
        shares = "  ".join(
            f"{key[:-2]} {best[key] / best['first_call_s']:4.0%}" for key in KEYS[1:]
        )
        print(
            f"{system:21s} {integrator:24s} {call:19s} first "
            + " ".join(f"{run['first_call_s']:5.2f}" for run in runs)
            + f" s; best: {shares}; {best['other_programs']} other programs",
            flush=True,
        )
    document = {
        "what": __doc__.splitlines()[0],
        "tree": args.tree or "this checkout",
        "rows": rows,
    }
    write_results(args.out, document)


if __name__ == "__main__":
    main()
