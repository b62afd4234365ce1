"""The demo's text output: the table of integrators, its header and legend, and JSON."""

from __future__ import annotations

import json
import math

import jax

import lievi

from .problems import REFERENCE_TOL, Problem

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


def format_table(rows: list[dict], problem: Problem) -> str:
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


LEGEND = """\
error at T: max |·| against the reference at the final time, for Π and for g.
rel. drift: max_k |q_k − q_0| / |q_0| of the energy ½ΠᵀI⁻¹Π + V(g), {invariants}.
  ‖gᵀg−I‖: Frobenius norm at T. DEL res.: max |D₂L_d + D₁L_d|
  over the trajectory (n/a: not variational, or fewer than 2 steps). Newton/step: mean
  iterations. result: 0 = success (lievi.RESULTS). wall time: 1st run = compile + run,
  2nd run = the compiled run alone."""


def device_description() -> str:
    device = jax.devices()[0]
    kind = getattr(device, "device_kind", "")
    text = f"{device} ({device.platform}"
    if kind and kind.lower() != device.platform:
        text += f", {kind}"
    return text + ")"


def header(h: float, n_steps: int, reference_time: float, problem: Problem) -> str:
    return "\n".join(
        [
            f"lievi demo: {problem.title}",
            *(f"  {line}" for line in problem.description),
            f"  h = {h:g},  n_steps = {n_steps},  T = {h * n_steps:g}",
            f"  reference: DOP853, rtol = atol = {REFERENCE_TOL:g} ({reference_time:.2f} s)",
            f"  device: {device_description()},  float64,  "
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
    problem: Problem,
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
