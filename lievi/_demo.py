"""`python -m lievi demo`: every integrator on a test problem, against a reference.

`--problem free-body` (default): the free rigid body of Hairer, Lubich & Wanner,
*Geometric Numerical Integration*, §VII.5 (`I = (2, 1, 2/3)`, `Π₀ = (cos 1.1, 0, sin 1.1)`,
`g₀ = I₃`, `h = 0.1`, `T = 100`). `--problem heavy-top`: an asymmetric heavy top with an
off-axis centre of mass (the same inertia, `m γ = 1`, `ρ = (0.3, −0.2, 0.5)`, a tilted
`g₀`), the paper's §7. Each integrator's run is compared with a DOP853 reference solution
(rtol = atol = 1e-13, computed once); one table row per integrator: errors at `T`, the
energy error and the drifts of the problem's conserved quantities, the DEL residual, Newton
iterations, the result code and wall times. `--plot` saves a figure (needs matplotlib,
imported only then), `--json` writes the table; both paths are checked before the run.

`--problem control` is an optimisation rather than a table of integrators: optimal
rest-to-rest reorientation of a rigid body with gradients through `simulate` (see
`lievi._demo_control`).

Adding an integrator to the demo is one row in `INTEGRATORS`; a problem is one `Problem`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lievi
from lievi import diagnostics

# (display name, integrator): one row each in the table and the plot.
INTEGRATORS: tuple[tuple[str, lievi.AbstractIntegrator], ...] = (
    ("DEP exp chart", lievi.DEP(chart="exp")),
    ("DEP Cayley chart", lievi.DEP(chart="cayley")),
    ("Moser–Veselov", lievi.MoserVeselov()),
    ("Lie–Poisson splitting", lievi.LiePoissonSplitting()),
    ("RK4 (non-geometric)", lievi.RK4()),
    ("Composition(MV), order 6", lievi.Composition(lievi.MoserVeselov(), order=6)),
    ("preprocessed DMV, order 6", lievi.PreprocessedMoserVeselov(order=6)),
)

# The HLW problem (Hairer, Lubich & Wanner, §VII.5).
INERTIA = (2.0, 1.0, 2.0 / 3.0)
THETA = 1.1
DEFAULT_H = 0.1
DEFAULT_STEPS = 1000  # T = 100 at h = 0.1
REFERENCE_TOL = 1e-13


def hlw_problem():
    """`(body, g0, m0)` of the Hairer–Lubich–Wanner rigid body."""
    body = lievi.RigidBody(jnp.array(INERTIA))
    m0 = jnp.array([math.cos(THETA), 0.0, math.sin(THETA)])
    return body, jnp.eye(3), m0


# The asymmetric heavy top: the HLW inertia about the fixed point, an off-axis centre of
# mass, nondimensional gravity, tilted initial attitude (the paper's §7).
CENTER_OF_MASS = (0.3, -0.2, 0.5)
TILT = (0.4, -0.3, 0.2)  # g₀ = exp(TILT^)


def heavy_top_problem():
    """`(top, g0, m0)` of the asymmetric heavy top."""
    top = lievi.heavy_top(jnp.array(INERTIA), 1.0, jnp.array(CENTER_OF_MASS), gravity=1.0)
    m0 = jnp.array([math.cos(THETA), 0.0, math.sin(THETA)])
    return top, lievi.SO3.exp(jnp.array(TILT)), m0


def _free_body_invariants(system, g, m):
    """The free body's Casimir |Π|² and spatial angular momentum gΠ."""
    return {
        "casimir_drift": diagnostics.relative_drift(diagnostics.casimirs(system, m)),
        "spatial_momentum_drift": diagnostics.relative_drift(
            diagnostics.spatial_momentum(system, g, m)
        ),
    }


def _heavy_top_invariants(system, g, m):
    """The heavy top's Casimirs of the reduced (Π, Γ) dynamics, Γ = gᵀe₃ the vertical in
    the body: |Γ|² (= 1) and Π·Γ = e₃·(gΠ), the vertical angular momentum."""
    gamma = g[:, 2, :]
    return {
        "gamma_norm_defect": jnp.max(jnp.abs(jnp.sum(gamma**2, axis=1) - 1)),
        "vertical_momentum_drift": diagnostics.relative_drift(jnp.sum(m * gamma, axis=1)),
    }


class Problem(NamedTuple):
    """A demo problem: the system and state, defaults, the integrators that apply, and
    its conserved quantities (table columns `(key, header 1, header 2, format)`)."""

    title: str
    description: tuple[str, ...]
    make: Callable
    default_h: float
    default_steps: int
    integrators: tuple
    invariants: Callable
    columns: tuple
    legend: str
    json: dict


PROBLEMS = {
    "free-body": Problem(
        title="free rigid body on SO(3), Hairer–Lubich–Wanner test problem",
        description=("inertia I = (2, 1, 2/3),  Π₀ = (cos 1.1, 0, sin 1.1),  g₀ = I₃",),
        make=hlw_problem,
        default_h=DEFAULT_H,
        default_steps=DEFAULT_STEPS,
        integrators=INTEGRATORS,
        invariants=_free_body_invariants,
        columns=(
            ("casimir_drift", "rel. drift", "Casimir", "{:.2e}"),
            ("spatial_momentum_drift", "rel. drift", "spat.mom", "{:.2e}"),
        ),
        legend="the Casimir |Π|², and the spatial momentum gΠ",
        json={
            "name": "Hairer–Lubich–Wanner rigid body",
            "inertia": list(INERTIA),
            "m0": [math.cos(THETA), 0.0, math.sin(THETA)],
            "g0": "identity",
        },
    ),
    "heavy-top": Problem(
        title="asymmetric heavy top on SO(3) (uniform gravity, off-axis centre of mass)",
        description=(
            "inertia I = (2, 1, 2/3) about the fixed point,  m γ = 1,  ρ = (0.3, −0.2, 0.5)",
            "Π₀ = (cos 1.1, 0, sin 1.1),  g₀ = exp((0.4, −0.3, 0.2)^)",
        ),
        make=heavy_top_problem,
        default_h=DEFAULT_H,
        default_steps=DEFAULT_STEPS,
        # The preprocessed DMV is a free-body method (its modified inertia has no potential).
        integrators=tuple(
            (n, i) for n, i in INTEGRATORS if not isinstance(i, lievi.PreprocessedMoserVeselov)
        ),
        invariants=_heavy_top_invariants,
        columns=(
            ("gamma_norm_defect", "Casimirs", "max||Γ|²−1|", "{:.2e}"),
            ("vertical_momentum_drift", "Casimirs", "Π·Γ drift", "{:.2e}"),
        ),
        legend=(
            "the Casimirs of the heavy top,\n  |Γ|² (max deviation from 1) and Π·Γ = e₃·(gΠ) "
            "(relative drift), Γ = gᵀe₃ the vertical in the body"
        ),
        json={
            "name": "asymmetric heavy top",
            "inertia": list(INERTIA),
            "mass_times_gravity": 1.0,
            "center_of_mass": list(CENTER_OF_MASS),
            "m0": [math.cos(THETA), 0.0, math.sin(THETA)],
            "g0": {"rotation_vector": list(TILT)},
        },
    ),
}
DEFAULT_PROBLEM = "free-body"


# --------------------------------------------------------------------------- arguments


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer ≥ 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer ≥ 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `demo` subcommand's options."""
    parser.add_argument(
        "--steps",
        type=_positive_int,
        default=None,
        metavar="N",
        help=f"number of steps (default {DEFAULT_STEPS}, i.e. T = 100 at the default h; "
        "control: 60 over the fixed T = 2)",
    )
    parser.add_argument(
        "--h",
        type=_positive_float,
        default=None,
        metavar="H",
        help=f"step size (default {DEFAULT_H}; not for control, where h = T/N)",
    )
    parser.add_argument(
        "--problem",
        choices=(*PROBLEMS, "control"),
        default=DEFAULT_PROBLEM,
        help=f"the test problem (default {DEFAULT_PROBLEM}; heavy-top: the asymmetric heavy "
        "top; control: optimal rest-to-rest reorientation, solved through the integrator)",
    )
    parser.add_argument(
        "--plot",
        metavar="FILE.png",
        default=None,
        help="save a figure: Π(t) against the reference, and |E − E₀| (needs matplotlib)",
    )
    parser.add_argument("--json", metavar="FILE.json", default=None, help="write the table as JSON")


# --------------------------------------------------------------------------- runs


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
    eye = jnp.eye(g.shape[-1], dtype=g.dtype)
    energy = diagnostics.energy(body, m, g)
    out = {
        "energy": energy,
        "energy_drift": diagnostics.relative_drift(energy),
        **invariants(body, g, m),
        "orthogonality_end": jnp.linalg.norm(g[-1].T @ g[-1] - eye),
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
    problem: Problem = PROBLEMS[DEFAULT_PROBLEM],
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


# --------------------------------------------------------------------------- output

# (key, header line 1, header line 2, format); the problem's conserved quantities go
# after the energy.
_LEADING = (
    ("error_m", "error at T", "Π", "{:.2e}"),
    ("error_g", "error at T", "g", "{:.2e}"),
    ("energy_drift", "rel. drift", "energy", "{:.2e}"),
)
_TRAILING = (
    ("orthogonality_end", "at T", "‖gᵀg−I‖", "{:.2e}"),
    ("del_residual_max", "max", "DEL res.", "{:.2e}"),
    ("newton_per_step", "", "Newton/step", "{:.2f}"),
    ("result", "", "result", "{:d}"),
    ("time_first_s", "wall time [s]", "1st run", "{:.3f}"),
    ("time_second_s", "wall time [s]", "2nd run", "{:.3f}"),
)


def _columns(problem: Problem) -> tuple:
    return _LEADING + tuple(problem.columns) + _TRAILING


def _cell(value, fmt: str) -> str:
    if value is None:
        return "n/a"
    return fmt.format(value)


def format_table(rows: list[dict], problem: Problem = PROBLEMS[DEFAULT_PROBLEM]) -> str:
    """The rows as an aligned text table (two header lines)."""
    columns = _columns(problem)
    name_width = max([len("integrator")] + [len(r["integrator"]) for r in rows])
    cells = [[_cell(r[key], fmt) for key, _, _, fmt in columns] for r in rows]
    widths = [
        max([len(bottom)] + [len(c[i]) for c in cells])
        for i, (_, _, bottom, _) in enumerate(columns)
    ]
    sep = "  "
    # Top header: each run of equal labels centred once over the columns it spans.
    spans, i = [], 0
    while i < len(columns):
        j = i
        while j + 1 < len(columns) and columns[j + 1][1] == columns[i][1]:
            j += 1
        span = sum(widths[i : j + 1]) + len(sep) * (j - i)
        spans.append(columns[i][1].center(span))
        i = j + 1
    top = sep.join([" " * name_width] + spans)
    bottom = sep.join(
        ["integrator".ljust(name_width)] + [b.rjust(w) for (_, _, b, _), w in zip(columns, widths)]
    )
    lines = [top.rstrip(), bottom, "-" * len(bottom)]
    for r, c in zip(rows, cells):
        row = [r["integrator"].ljust(name_width)] + [x.rjust(w) for x, w in zip(c, widths)]
        lines.append(sep.join(row))
    return "\n".join(lines)


_LEGEND = """\
error at T: max |·| against the reference at the final time, for Π and for g.
rel. drift: max_k |q_k − q_0| / |q_0| of the energy ½ΠᵀI⁻¹Π + V(g), {invariants}.
  ‖gᵀg−I‖: Frobenius norm at T. DEL res.: max |D₂L_d + D₁L_d|
  over the trajectory (n/a: not variational, or fewer than 2 steps). Newton/step: mean
  iterations. result: 0 = success (lievi.RESULTS). wall time: 1st run = compile + run,
  2nd run = the compiled run alone."""


def _device_description() -> str:
    device = jax.devices()[0]
    kind = getattr(device, "device_kind", "")
    text = f"{device} ({device.platform}"
    if kind and kind.lower() != device.platform:
        text += f", {kind}"
    return text + ")"


def _header(
    h: float, n_steps: int, reference_time: float, problem: Problem = PROBLEMS[DEFAULT_PROBLEM]
) -> str:
    return "\n".join(
        [
            f"lievi demo: {problem.title}",
            *(f"  {line}" for line in problem.description),
            f"  h = {h:g},  n_steps = {n_steps},  T = {h * n_steps:g}",
            f"  reference: DOP853, rtol = atol = {REFERENCE_TOL:g} ({reference_time:.2f} s)",
            f"  device: {_device_description()},  float64,  "
            f"lievi {lievi.__version__}, jax {jax.__version__}",
        ]
    )


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None  # strict JSON has no NaN/inf
    return value


def write_json(
    path: str,
    h: float,
    n_steps: int,
    rows: list[dict],
    problem: Problem = PROBLEMS[DEFAULT_PROBLEM],
) -> None:
    document = {
        "problem": {
            **problem.json,
            "h": h,
            "n_steps": n_steps,
            "T": h * n_steps,
        },
        "reference": {"method": "DOP853", "rtol": REFERENCE_TOL, "atol": REFERENCE_TOL},
        "device": str(jax.devices()[0]),
        "platform": jax.devices()[0].platform,
        "rows": [{k: _json_safe(v) for k, v in row.items()} for row in rows],
    }
    with open(path, "w", encoding="utf-8") as f:
        json.dump(document, f, indent=2, ensure_ascii=False)
        f.write("\n")


def save_plot(
    path: str,
    ts,
    m_ref,
    energy_ref,
    runs: list[tuple[str, Any, Any]],
    title: str = "Hairer–Lubich–Wanner rigid body, I = (2, 1, 2/3)",
) -> None:
    """Left: Π components against t (reference in grey); right: |E − E₀| against t.

    `runs`: `(name, Solution, energy trajectory)` per integrator. matplotlib is imported
    here, so the package itself does not need it.
    """
    try:
        import matplotlib
    except ImportError:
        raise SystemExit(
            "--plot needs matplotlib: pip install matplotlib (or lievi[plot])."
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ts = np.asarray(ts)
    energy0 = float(energy_ref[0])
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ("--", ":", "-.", (0, (5, 1)), (0, (3, 1, 1, 1)))

    fig = plt.figure(figsize=(13, 6.5), layout="constrained")
    grid = fig.add_gridspec(3, 2)
    axes = []
    for i in range(3):
        ax = fig.add_subplot(grid[i, 0], sharex=axes[0] if axes else None)
        axes.append(ax)
        ax.plot(ts, m_ref[:, i], color="black", lw=3, alpha=0.3, label="reference (DOP853)")
        for j, (name, solution, _) in enumerate(runs):
            ax.plot(
                ts,
                np.asarray(solution.m[:, i]),
                color=colours[j % len(colours)],
                ls=styles[j % len(styles)],
                lw=1.2,
                label=name,
            )
        ax.set_ylabel(f"$\\Pi_{i + 1}$")
        ax.grid(True, alpha=0.3)
        if i < 2:
            ax.tick_params(labelbottom=False)
    axes[0].set_title("body momentum Π(t)")
    low, high = axes[0].get_ylim()
    axes[0].set_ylim(low, high + 0.35 * (high - low))  # room for the legend
    axes[0].legend(fontsize="small", loc="upper right", ncol=min(3, len(runs) + 1))
    axes[-1].set_xlabel("t")

    def positive(x):  # log axes: drop exact zeros (t = 0)
        x = np.abs(np.asarray(x) - energy0)
        return np.where(x > 0, x, np.nan)

    ax = fig.add_subplot(grid[:, 1])
    for j, (name, _, energy) in enumerate(runs):
        ax.semilogy(ts, positive(energy), color=colours[j % len(colours)], lw=1.0, label=name)
    ax.semilogy(
        ts, positive(energy_ref), color="black", alpha=0.3, lw=1.0, label="reference (DOP853)"
    )
    ax.set_title(f"energy error |E − E₀|  (E₀ = {energy0:.6g})")
    ax.set_xlabel("t")
    ax.set_ylabel("|E − E₀|")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize="small", loc="lower right")

    h = ts[1] - ts[0] if len(ts) > 1 else float("nan")
    fig.suptitle(f"lievi: {title}, h = {h:g}, T = {ts[-1]:g}")
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- entry point


def check_output_path(option: str, path: str) -> str | None:
    """Why `path` cannot be written (a message naming `option`), or `None` if it can.

    Checked before the run, so a typo does not cost the whole computation.
    """
    directory = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        return f"{option} {path!r} is a directory; give a file name."
    if not os.path.isdir(directory):
        return f"{option} {path!r}: the directory {directory!r} does not exist; create it first."
    if not os.access(directory, os.W_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        return f"{option} {path!r}: not writable; choose another location."
    return None


def main(args: argparse.Namespace) -> int:
    """Run the demo with the parsed `demo` options; returns the exit status.

    0 when every integrator succeeded (result code 0) and every requested output was
    written; 1 when an integrator failed or an output could not be written (the others
    are still written); 2 when an output path is unusable, found before the run.
    """
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "the demo needs float64: run `python -m lievi demo`, or call "
            "jax.config.update('jax_enable_x64', True) before creating arrays."
        )
    problem_name = getattr(args, "problem", DEFAULT_PROBLEM)
    outputs = [
        (option, path) for option, path in (("--json", args.json), ("--plot", args.plot)) if path
    ]
    problems = [msg for option, path in outputs if (msg := check_output_path(option, path))]
    if args.plot and not problems:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            problems.append("--plot needs matplotlib: pip install matplotlib (or lievi[plot]).")
    if problems:
        for message in problems:
            print(f"lievi demo: error: {message}", file=sys.stderr)
        return 2
    if problem_name == "control":  # an optimisation, not a table of integrators
        from . import _demo_control

        return _demo_control.main(args)

    problem = PROBLEMS[problem_name]
    h = float(args.h) if args.h is not None else problem.default_h
    n_steps = int(args.steps) if args.steps is not None else problem.default_steps
    body, g0, m0 = problem.make()
    ts = h * np.arange(n_steps + 1)

    start = time.perf_counter()
    g_ref, m_ref = lievi.reference_solution(
        body, g0, m0, ts, rtol=REFERENCE_TOL, atol=REFERENCE_TOL
    )
    reference_time = time.perf_counter() - start

    print(_header(h, n_steps, reference_time, problem), flush=True)
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
    print(_LEGEND.format(invariants=problem.legend))
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
                eqx.filter_jit(diagnostics.energy)(body, jnp.asarray(m_ref), jnp.asarray(g_ref))
            )
            title = problem.title.split(" (")[0] + ", I = (2, 1, 2/3)"
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
