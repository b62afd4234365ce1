"""Which collectives a sharded batch compiles to: the communication of a multi-device or
multi-process run, read off XLA's compiled program.

The batch is placed on 2 forced CPU devices with `lievi.shard_batch` (a multi-process
run compiles the same program over the devices of all processes), and the compiled HLO of
each computation is searched for XLA's collective operations. Each is listed with where
it sits: inside the step loop (paid every step) or outside it (once per run).

    python benchmarks/collectives.py

Writes `benchmarks/results/collectives.json`.
"""

from __future__ import annotations

import json
import os
import pathlib
import re

os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
COLLECTIVES = ("all-reduce", "all-gather", "reduce-scatter", "all-to-all", "collective-permute")
B = 64


def _collectives(compiled_text: str) -> dict[str, int]:
    """Count of each collective op in the compiled program (start/done pairs once)."""
    counts = {}
    for op in COLLECTIVES:
        found = re.findall(rf"= [^\n]*? {op}(?:-start)?\(", compiled_text)
        if found:
            counts[op] = len(found)
    return counts


def _computations(compiled_text: str) -> dict[str, str]:
    """The compiled program's computations, by name: `{name: its text}`."""
    blocks = {}
    for block in re.split(r"\n(?=\S)", compiled_text):
        match = re.match(r"(?:ENTRY )?%?([\w.\-]+) ", block)
        if match:
            blocks[match.group(1)] = block
    return blocks


def _called(block: str) -> set[str]:
    """The computations `block` calls (loop bodies and conditions, branches, fusions, …)."""
    names = set(re.findall(r"(?:condition|body|to_apply|calls)=%?([\w.\-]+)", block))
    for group in re.findall(r"branch_computations=\{([^}]*)\}", block):
        names |= {n.strip().lstrip("%") for n in group.split(",")}
    return names


def _in_loops(compiled_text: str) -> dict[str, int]:
    """The collectives inside `while` loops (the step loop, the Newton tail), counting
    everything a loop's body or condition calls, transitively."""
    blocks = _computations(compiled_text)
    roots = set()
    for block in blocks.values():
        roots |= set(re.findall(r"while\([^\n]*?(?:condition|body)=%?([\w.\-]+)", block))
        roots |= set(re.findall(r"body=%?([\w.\-]+)", block))
    seen, todo = set(), list(roots)
    while todo:
        name = todo.pop()
        if name in seen or name not in blocks:
            continue
        seen.add(name)
        todo.extend(_called(blocks[name]))
    counts: dict[str, int] = {}
    for name in seen:
        for op, count in _collectives(blocks[name]).items():
            counts[op] = counts.get(op, 0) + count
    return counts


def main() -> None:
    rng = np.random.default_rng(0)
    inertia = jnp.asarray(rng.uniform(0.5, 2.0, (B, 3)))
    m0 = jnp.asarray(rng.normal(size=(B, 3)))
    g0 = jnp.broadcast_to(jnp.eye(3), (B, 3, 3))
    inertia, m0, g0 = lievi.shard_batch((inertia, m0, g0))

    def so3(inertia, m0, g0, throw):
        return lievi.simulate_batch(
            jax.vmap(lievi.RigidBody)(inertia),
            lievi.DEP(),
            g0,
            m0,
            h=0.1,
            n_steps=100,
            save=lievi.Save(every=10),
            throw=throw,
        )

    def loss(inertia, m0, g0):
        return jnp.sum(so3(inertia, m0, g0, False).m[:, -1] * jnp.array([1.0, 2.0, 3.0]))

    body_se3 = lievi.RigidBodySE3(inertia=jnp.array([2.0, 1.0, 0.5]), mass=1.0)
    m0_se3 = lievi.shard_batch(jnp.asarray(rng.normal(size=(B, 6))))
    g0_se3 = lievi.shard_batch(jnp.broadcast_to(jnp.eye(4), (B, 4, 4)))

    def se3(m0, g0):
        return lievi.simulate_batch(
            body_se3,
            lievi.DEP(),
            g0,
            m0,
            h=0.1,
            n_steps=100,
            save=lievi.Save(every=10),
            throw=False,
        )

    cases = {
        "SO(3) DEP forward, throw=False": (lambda *a: so3(*a, False), (inertia, m0, g0)),
        "SO(3) DEP forward, throw=True": (lambda *a: so3(*a, True), (inertia, m0, g0)),
        "SO(3) DEP gradient of a summed loss": (jax.grad(loss), (inertia, m0, g0)),
        "SE(3) DEP forward, throw=False": (se3, (m0_se3, g0_se3)),
    }
    report = {"devices": [str(d) for d in jax.devices()], "batch": B, "cases": {}}
    for name, (fn, args) in cases.items():
        text = jax.jit(fn).lower(*args).compile().as_text()
        entry = {"total": _collectives(text), "inside_loops": _in_loops(text)}
        report["cases"][name] = entry
        print(f"{name}: {entry}")
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / "collectives.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
