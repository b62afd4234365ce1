"""What an XLA CPU flag trades: first-call time against run time, per flag set.

XLA's CPU backend reads process-wide options from the environment variable `XLA_FLAGS`,
so each flag set runs in fresh processes. For every flag set, alternately, round after
round:

- **first call**: a fresh process builds the system and makes its first `lievi.simulate`
  call (2000 steps, the final state saved), as `benchmarks/first_call.py` does: tracing,
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
import pathlib
import platform
import subprocess
import sys

RESULTS = pathlib.Path(__file__).resolve().parent / "results"

SETUP = """
import json, time, jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", None)
import jax.numpy as jnp, numpy as np, lievi
"""

FIRST_CALL = (
    SETUP
    + """
start = time.perf_counter()
body = {system}
sol = lievi.simulate(body, {method}, {g0}, {m0}, h=0.05, n_steps=2000, save_every=2000)
jax.block_until_ready(sol.m)
print(json.dumps(time.perf_counter() - start))
"""
)

RUN_TIME = (
    SETUP
    + """
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

SO3 = ("lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))", "jnp.eye(3)", "jnp.array([0.3, -0.2, 0.5])")
SE3 = (
    "lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)",
    "jnp.eye(4)",
    "jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])",
)
CASES = {
    "RigidBody (SO(3)), DEP exp": (*SO3, "lievi.DEP()", 65536, 100),
    "RigidBodySE3, DEP exp": (*SE3, "lievi.DEP()", 4096, 200),
    "RigidBodySE3, DEP cayley": (*SE3, 'lievi.DEP(chart="cayley")', 4096, 200),
}


def _python(code: str, flags: str):
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    if flags:
        env["XLA_FLAGS"] = flags
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def first_call(case: str, flags: str) -> float:
    system, g0, m0, method, _, _ = CASES[case]
    code = FIRST_CALL.format(system=system, method=method, g0=g0, m0=m0)
    return _python(code, flags)


def run_rates(flags: str) -> dict:
    cases = (
        "["
        + ", ".join(
            f"({name!r}, {system}, {method}, {g0}, {m0}, {batch}, {steps})"
            for name, (system, g0, m0, method, batch, steps) in CASES.items()
        )
        + "]"
    )
    return _python(RUN_TIME.format(cases=cases), flags)


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
            for case in CASES:
                row["first_call_s"].setdefault(case, []).append(first_call(case, flags))
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
