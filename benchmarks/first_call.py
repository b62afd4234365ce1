"""What a new script pays before its first result: building the system and the first
`lievi.simulate` call, in a fresh process each time (nothing compiled yet, JAX's persistent
compilation cache off), by wall clock.

Each case runs in its own subprocess: `import lievi` (not timed), then the system's
constructor and one `simulate` call of 2000 steps saving the final state, with
`jax.block_until_ready` (timed). The time is tracing, lowering and compiling the run's
program and the small programs of its checks and output, plus the run itself (a few
milliseconds here). `--tree PATH` times another checkout of lievi (e.g. a `git worktree`
of an earlier commit), so that a change can be measured before and after, alternately.

    python benchmarks/first_call.py [--rounds 3] [--tree PATH] [--out first_call]

Writes `benchmarks/results/<out>.json`.
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
import time, jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", None)
import jax.numpy as jnp, lievi
"""

CASES = {
    "RigidBody (SO(3)), DEP exp": (
        "lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))",
        "jnp.eye(3)",
        "jnp.array([0.3, -0.2, 0.5])",
    ),
    "RigidBodySE3, DEP exp": (
        "lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)",
        "jnp.eye(4)",
        "jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])",
    ),
}

TIMED = """
start = time.perf_counter()
body = {system}
sol = lievi.simulate(body, lievi.DEP(), {g0}, {m0}, h=0.05, n_steps=2000, save_every=2000)
jax.block_until_ready(sol.m)
print(time.perf_counter() - start)
"""


def first_call(case: str, tree: str | None) -> float:
    system, g0, m0 = CASES[case]
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = tree
    code = SETUP + TIMED.format(system=system, g0=g0, m0=m0)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    return float(out.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--tree", default=None, help="another checkout of lievi to time")
    parser.add_argument("--out", default="first_call")
    args = parser.parse_args()
    rows = []
    for case in CASES:
        times = [first_call(case, args.tree) for _ in range(args.rounds)]
        rows.append({"case": case, "first_call_s": times})
        print(f"{case:32s} " + "  ".join(f"{t:6.2f}" for t in times) + " s")
    document = {
        "what": "system constructor + first simulate (2000 steps, final state), fresh process",
        "tree": args.tree or "this checkout",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
        "load_average": os.getloadavg(),
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.out}.json"
    path.write_text(json.dumps(document, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
