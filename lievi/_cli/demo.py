"""`python -m lievi demo`: every integrator on a test problem, against a reference.

Each integrator's run is compared with a DOP853 reference solution (rtol = atol = 1e-13,
computed once); one table row per integrator: errors at `T`, the energy error and the
drifts of the problem's conserved quantities, the DEL residual, Newton iterations, the
result code and wall times. `--plot` saves a figure (needs matplotlib, imported only
then), `--json` writes the table; both paths are checked before the run
(`arguments.check_arguments`).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lievi
from lievi import diagnostics

from .plots import save_plot
from .problems import PROBLEMS, REFERENCE_TOL, Problem
from .report import LEGEND, format_table, header, write_json


def _timed_simulate(body, integrator, g0, m0, h, n_steps):
    """Run twice: the first call compiles and runs, the second only runs."""
    times = []
    for _ in range(2):
        start = time.perf_counter()
        solution = lievi.simulate(body, integrator, g0, m0, h=h, n_steps=n_steps, throw=False)
        solution = jax.block_until_ready(solution)
        times.append(time.perf_counter() - start)
    return solution, times[0], times[1]


@eqx.filter_jit
def _diagnostics(body, integrator, g, m, h, invariants):
    """All trajectory diagnostics in one compiled call (eager `del_residual` is slow)."""
    # The rotation blocks: `g` itself on SO(3), each pose's on SE(3) (several bodies: each).
    R = g[-1][..., :3, :3]
    eye = jnp.eye(3, dtype=g.dtype)
    energy = diagnostics.energy(body, g, m)
    out = {
        "energy": energy,
        "energy_drift": diagnostics.relative_drift(energy),
        **invariants(body, g, m),
        "orthogonality_end": jnp.max(
            jnp.linalg.norm(jnp.swapaxes(R, -1, -2) @ R - eye, axis=(-2, -1))
        ),
    }
    if isinstance(integrator, lievi.AbstractVariationalIntegrator) and g.shape[0] >= 3:
        out["del_residual_max"] = jnp.max(jnp.abs(diagnostics.del_residual(body, integrator, g, h)))
    return out


def run_integrator(
    name,
    integrator,
    body,
    g0,
    m0,
    h,
    n_steps,
    g_ref,
    m_ref,
    problem: Problem,
) -> tuple[dict, Any]:
    """One table row (a dict of plain Python numbers), and `(Solution, energy)` to plot."""
    solution, first_time, second_time = _timed_simulate(body, integrator, g0, m0, h, n_steps)
    g, m = solution.g, solution.m
    diag = _diagnostics(body, integrator, g, m, jnp.asarray(h, m.dtype), problem.invariants)
    energy = np.asarray(diag.pop("energy"))
    diag = {k: float(v) for k, v in diag.items()}
    row = {
        "integrator": name,
        "order": int(integrator.order()),
        "error_m": float(np.max(np.abs(np.asarray(m[-1]) - m_ref[-1]))),
        "error_g": float(np.max(np.abs(np.asarray(g[-1]) - g_ref[-1]))),
        "energy_drift": diag["energy_drift"],
        **{key: diag[key] for key, *_ in problem.columns},
        "orthogonality_end": diag["orthogonality_end"],
        # None: not variational (no discrete Lagrangian to check), or fewer than 2 steps.
        "del_residual_max": diag.get("del_residual_max"),
        "newton_per_step": float(solution.stats["total_newton_iterations"]) / n_steps,
        "result": int(solution.result),
        "failed_step": int(solution.stats["failed_step"]),
        "time_first_s": first_time,
        "time_second_s": second_time,
    }
    return row, (solution, energy)


def main(args: argparse.Namespace) -> int:
    """Run every integrator of `args.problem` (options checked by `check_arguments`);
    returns the exit status: 0 when every integrator succeeded (result code 0) and every
    requested output was written; 1 when an integrator failed or an output could not be
    written (the others are still written)."""
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "the demo needs float64: run `python -m lievi demo`, or call "
            "jax.config.update('jax_enable_x64', True) before creating arrays."
        )
    problem = PROBLEMS[args.problem]
    outputs = args.json or args.plot
    h = float(args.h) if args.h is not None else problem.default_h
    n_steps = int(args.steps) if args.steps is not None else problem.default_steps
    body, g0, m0 = problem.make()
    ts = h * np.arange(n_steps + 1)

    start = time.perf_counter()
    g_ref, m_ref = lievi.reference_solution(
        body, g0, m0, ts, rtol=REFERENCE_TOL, atol=REFERENCE_TOL
    )
    reference_time = time.perf_counter() - start

    print(header(h, n_steps, reference_time, problem), flush=True)
    print(flush=True)

    rows, runs = [], []
    for name, integrator in problem.integrators:
        row, (solution, energy) = run_integrator(
            name, integrator, body, g0, m0, h, n_steps, g_ref, m_ref, problem
        )
        rows.append(row)
        runs.append((name, solution, energy))

    print(format_table(rows, problem))
    print()
    print(LEGEND.format(invariants=problem.legend))
    for row in rows:
        if row["result"] != lievi.RESULTS.successful:
            print(
                f"\n{row['integrator']}: failed at step {row['failed_step']}: "
                f"{lievi.RESULTS.message(row['result'])}"
            )

    if outputs:
        print()
    written = True
    # Each output on its own: one that cannot be written does not lose the other.
    if args.json:
        try:
            write_json(args.json, h, n_steps, rows, problem)
            print(f"table written to {args.json}")
        except OSError as error:
            written = False
            print(
                f"lievi demo: error: --json {args.json!r} could not be written: {error}",
                file=sys.stderr,
            )
    if args.plot:
        try:
            energy_ref = np.asarray(
                eqx.filter_jit(diagnostics.energy)(body, jnp.asarray(g_ref), jnp.asarray(m_ref))
            )
            title = problem.title.split(" (")[0] + problem.plot_note
            save_plot(args.plot, ts, m_ref, energy_ref, runs, title)
            print(f"figure written to {args.plot}")
        except OSError as error:
            written = False
            print(
                f"lievi demo: error: --plot {args.plot!r} could not be written: {error}",
                file=sys.stderr,
            )
    ok = all(r["result"] == lievi.RESULTS.successful for r in rows)
    return 0 if ok and written else 1
