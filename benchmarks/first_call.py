"""What a new script pays before its first result: building the system and the first
`lievi.simulate` call, in a fresh process each time (nothing compiled yet, JAX's persistent
compilation cache off), by wall clock.

Each case runs in its own subprocess: `import lievi` (not timed), then the system's
constructor and one `simulate` call of 2000 steps saving the final state, with
`jax.block_until_ready` (timed); the `simulate_batch` cases make one call for 64 bodies
(momenta within 10 % of one value), 100 steps, every step saved. The time is tracing,
lowering and compiling the run's program and the small programs of its checks and output,
plus the run itself (a few milliseconds here). Also reported: how many programs XLA
compiled in the timed part and their total compile time (JAX's monitoring event
`/jax/core/compile/backend_compile_duration`), which move far less with the machine's
load than the wall clock. `--tree PATH` times another checkout of lievi (e.g. a `git worktree`
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
compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **_: compiles.append(seconds)
    if event == "/jax/core/compile/backend_compile_duration" else None
)
"""

CASES = {
    "RigidBody (SO(3)), DEP exp": (
        "lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))",
        "jnp.eye(3)",
        "jnp.array([0.3, -0.2, 0.5])",
        "lievi.DEP()",
    ),
    "RigidBodySE3, DEP exp": (
        "lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)",
        "jnp.eye(4)",
        "jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])",
        "lievi.DEP()",
    ),
    "RigidBodySE3, DEP cayley": (
        "lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)",
        "jnp.eye(4)",
        "jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])",
        'lievi.DEP(chart="cayley")',
    ),
    "RigidBody (SO(3)), DEP exp, simulate_batch": (
        "lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))",
        "jnp.eye(3)",
        "jnp.array([0.3, -0.2, 0.5])",
        "lievi.DEP()",
    ),
    "GeneralizedRigidBody SO(4), DEP cayley, simulate_batch": (
        "lievi.GeneralizedRigidBody(jnp.array([1.0, 1.5, 2.0, 2.5]))",
        "jnp.eye(4)",
        "jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])",
        'lievi.DEP(chart="cayley")',
    ),
}

TIMED = """
start = time.perf_counter()
body = {system}
sol = lievi.simulate(body, {method}, {g0}, {m0}, h=0.05, n_steps=2000, save_every=2000)
jax.block_until_ready(sol.m)
print(time.perf_counter() - start, len(compiles), sum(compiles))
"""


TIMED_BATCH = """
momenta = {m0} * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(0), (64,) + {m0}.shape))
start = time.perf_counter()
body = {system}
sol = lievi.simulate_batch(body, {method}, {g0}, momenta, h=0.05, n_steps=100, save_every=1)
jax.block_until_ready(sol.m)
print(time.perf_counter() - start, len(compiles), sum(compiles))
"""


def first_and_best(repeats: int) -> str:
    """Code that times `call()` (defined before it) in a fresh process: the first call and
    the best of `repeats` repeats, printed as JSON (`first_call_s`, `run_s`) on its last
    line, for `run_in_checkout`."""
    return f"""
def timed():
    start = time.perf_counter()
    jax.block_until_ready(call())
    return time.perf_counter() - start


first = timed()
run = min(timed() for _ in range({repeats}))
print(json.dumps({{"first_call_s": first, "run_s": run}}))
"""


def run_in_checkout(code: str, tree: str | None = None, xla_flags: str | None = None) -> str:
    """Run `code` in a fresh `python -c` on the checkout `tree` (default: this one) and
    return the last line it printed. `xla_flags`: the process's `XLA_FLAGS` (`""`: none;
    `None`: as in this process)."""
    env = dict(os.environ)
    if xla_flags is not None:
        env.pop("XLA_FLAGS", None)
        if xla_flags:
            env["XLA_FLAGS"] = xla_flags
    # `python -c` puts its working directory first on the path, ahead of `PYTHONPATH`: run
    # in the checkout timed (`--tree`, else this one), or its `lievi` is not the one imported.
    root = str(pathlib.Path(tree).resolve()) if tree is not None else str(RESULTS.parent.parent)
    env["PYTHONPATH"] = root
    out = subprocess.run(
        [sys.executable, "-c", code + f"\nassert lievi.__file__.startswith({root!r})"],
        env=env,
        cwd=root,
        capture_output=True,
        text=True,
        check=True,
    )
    return out.stdout.strip().splitlines()[-1]


def write_results(name: str, document: dict) -> None:
    """`document`, with the machine and its load average, as `benchmarks/results/<name>.json`."""
    document = {
        **document,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
        "load_average": os.getloadavg(),
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(document, indent=2))
    print(f"wrote {path}")


def first_call(case: str, tree: str | None = None, xla_flags: str | None = None) -> dict:
    """One fresh process's first call of `case`: wall clock, programs compiled, XLA time."""
    system, g0, m0, method = CASES[case]
    template = TIMED_BATCH if case.endswith("simulate_batch") else TIMED
    code = SETUP + template.format(system=system, g0=g0, m0=m0, method=method)
    seconds, programs, compile_s = run_in_checkout(code, tree, xla_flags).split()
    return {"first_call_s": float(seconds), "programs": int(programs), "xla_s": float(compile_s)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--tree", default=None, help="another checkout of lievi to time")
    parser.add_argument("--out", default="first_call")
    args = parser.parse_args()
    rows = []
    for case in CASES:
        runs = [first_call(case, args.tree) for _ in range(args.rounds)]
        row = {key: [run[key] for run in runs] for key in runs[0]}
        rows.append({"case": case, **row})
        print(
            f"{case:56s} "
            + "  ".join(f"{t:6.2f}" for t in row["first_call_s"])
            + f" s; {row['programs'][-1]} programs compiled, XLA "
            + "  ".join(f"{t:5.2f}" for t in row["xla_s"])
            + " s"
        )
    document = {
        "what": "system constructor + first simulate (2000 steps, final state), or first "
        "simulate_batch (64 bodies, 100 steps, every step saved), fresh process",
        "tree": args.tree or "this checkout",
        "rows": rows,
    }
    write_results(args.out, document)


if __name__ == "__main__":
    main()
