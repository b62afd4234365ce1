"""What an XLA CPU flag trades: first-call time against run time, per flag set.

XLA's CPU backend reads process-wide options from the environment variable `XLA_FLAGS`,
so each flag set runs in fresh processes. For every flag set, alternately, round after
round:

- **first call**: a fresh process builds the system and makes its first `lievi.simulate`
  call (2000 steps, the final state saved), by `benchmarks/first_call.py`'s own code: tracing,
  compiling the run's program and those of its checks, and the run. Free rigid body on
  SO(3) and free `RigidBodySE3`, `DEP()` (exp chart) and `DEP(chart="cayley")` on SE(3);
- **run time** after compiling (best of 3): one body, 20000 steps; a batch
  (`simulate_batch`, 4096 SE(3) bodies × 200 steps, 65536 SO(3) bodies × 100 steps),
  reported in body-steps/s.

The flag sets: the default (`XLA_FLAGS` unset) and `--xla_cpu_use_fusion_emitters=false`
(XLA's earlier loop emitters in place of its fusion emitters), or those given.

    python benchmarks/xla_cpu_flags.py [--rounds 2] [--flags "" "--xla_cpu_use_fusion_emitters=false"]
                                       [--out xla_cpu_flags]

Writes `benchmarks/results/<out>.json`. Run it on an idle machine: both figures move with
the load.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys

from first_call import CASES, RESULTS, SETUP, first_call, run_in_checkout

RUN_TIME = (
    SETUP
    + """
import json, numpy as np

def best(run, rounds=3):
    jax.block_until_ready(run())
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        jax.block_until_ready(run())
        times.append(time.perf_counter() - start)
    return min(times)

rng = np.random.default_rng(0)
rates = {{}}
for name, body, method, g0, m0, batch, steps in {cases}:
    g0, m0 = jnp.asarray(g0), jnp.asarray(m0)
    one = lambda: lievi.simulate(body, method, g0, m0, h=0.05, n_steps=20000,
                                 save_every=20000).m
    rates[name + ", one body"] = 20000 / best(one)
    gb = jnp.broadcast_to(g0, (batch,) + g0.shape)
    mb = m0 * (1 + 0.05 * jnp.asarray(rng.standard_normal((batch,) + m0.shape)))
    many = lambda: lievi.simulate_batch(body, method, gb, mb, h=0.05, n_steps=steps,
                                        save_every=steps).m
    rates[f"{{name}}, batch {{batch}}"] = batch * steps / best(many)
print(json.dumps(rates))
"""
)

# `first_call.py`'s cases timed here, with the batch and steps of their throughput runs.
BATCHES = {
    "RigidBody (SO(3)), DEP exp": (65536, 100),
    "RigidBodySE3, DEP exp": (4096, 200),
    "RigidBodySE3, DEP cayley": (4096, 200),
}


def run_rates(flags: str) -> dict:
    cases = (
        "["
        + ", ".join(
            f"({name!r}, {system}, {method}, {g0}, {m0}, {batch}, {steps})"
            for name, (batch, steps) in BATCHES.items()
            for system, g0, m0, method in (CASES[name],)
        )
        + "]"
    )
    return json.loads(run_in_checkout(RUN_TIME.format(cases=cases), xla_flags=flags))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--flags", nargs="+", default=["", "--xla_cpu_use_fusion_emitters=false"])
    parser.add_argument("--out", default="xla_cpu_flags")
    args = parser.parse_args()
    load = os.getloadavg()
    rows = {flags: {"first_call_s": {}, "body_steps_per_s": {}} for flags in args.flags}
    for round_ in range(args.rounds):
        for flags in args.flags:
            row = rows[flags]
            for case in BATCHES:
                seconds = first_call(case, xla_flags=flags)["first_call_s"]
                row["first_call_s"].setdefault(case, []).append(seconds)
            for name, rate in run_rates(flags).items():
                row["body_steps_per_s"].setdefault(name, []).append(rate)
            label = flags or "(default)"
            print(f"round {round_ + 1}, {label}:")
            for case, times in row["first_call_s"].items():
                print(f"  first call {case:28s} {times[-1]:6.2f} s")
            for name, rates in row["body_steps_per_s"].items():
                print(f"  run {name:40s} {rates[-1]:.3e} body-steps/s")
    document = {
        "description": __doc__.splitlines()[0],
        "command": "python benchmarks/xla_cpu_flags.py " + " ".join(sys.argv[1:]),
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
