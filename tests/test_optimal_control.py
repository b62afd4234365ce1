"""Optimal control through the forced variational integrator: rest-to-rest reorientation.

The problem, its closed-form optimum for a spherical body (the eigenaxis manoeuvre,
`J* = 12 j² θ_f² / T³`, and the discrete optimum's `J_d/J* − 1 = 1/(N² − 1)`), and the
solver (augmented Lagrangian on the terminal defect, inner `optax.lbfgs`, gradients through
`lievi.simulate`) are in `lievi._demo_control`, which `python -m lievi demo --problem
control` runs; here they are checked.
"""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from lievi import _demo
from lievi.__main__ import build_parser
from lievi._demo_control import AXIS, spacecraft_manoeuvre, sphere_optimum


def test_sphere_discrete_optimum_is_the_eigenaxis_manoeuvre():
    """At a coarse step: on the eigenaxis to round-off, and `J_d/J* − 1 = 1/(N² − 1)`."""
    n = 16
    r = sphere_optimum(n)
    assert r["defect"] < 1e-12
    assert r["off_axis"] < 1e-9
    assert abs(r["cost_error"] - 1 / (n**2 - 1)) < 1e-6 / n**2, r["cost_error"]
    assert r["profile_error"] < 1 / n**2, r["profile_error"]


@pytest.mark.slow
def test_sphere_discrete_optimum_converges_to_the_closed_form():
    ns = [16, 32, 64, 128]
    results = [sphere_optimum(n) for n in ns]
    cost_errors = [r["cost_error"] for r in results]
    order = -np.polyfit(np.log(ns), np.log(cost_errors), 1)[0]
    assert abs(order - 2) < 0.05, (order, cost_errors)
    assert cost_errors[-1] <= 1e-4, cost_errors
    profile_errors = [r["profile_error"] for r in results]
    assert profile_errors[-1] <= 1e-4, profile_errors
    assert max(r["off_axis"] for r in results) < 1e-9  # eigenaxis
    assert max(r["defect"] for r in results) < 1e-12  # at rest at the target


@pytest.mark.slow
def test_asymmetric_spacecraft_reaches_the_target():
    r = spacecraft_manoeuvre(60)  # re-simulated with throw=True
    assert r["attitude_error"] <= 1e-6, r["attitude_error"]
    assert r["final_momentum"] <= 1e-6, r["final_momentum"]
    # The gyroscopic coupling moves the optimum off the eigenaxis (unlike the sphere's).
    assert r["off_axis_share"] > 1e-2, r["off_axis_share"]
    u = r["u"]
    assert float(jnp.max(jnp.abs(u - (u @ AXIS)[:, None] * AXIS))) > 1e-2


def test_control_demo_rejects_a_step_size(capsys):
    """`h = T/N` in the control demo: `--h` is refused with a message naming `--steps`."""
    args = build_parser().parse_args(["demo", "--problem", "control", "--h", "0.1"])
    assert _demo.main(args) == 2
    assert "--steps" in capsys.readouterr().err


@pytest.mark.slow
def test_control_demo(tmp_path, capsys, monkeypatch):
    """`python -m lievi demo --problem control` end to end (small N), JSON and plot."""
    pytest.importorskip("matplotlib")
    from lievi import _demo_control

    monkeypatch.setattr(_demo_control, "SPHERE_STEPS", (12,))
    table, plot = tmp_path / "control.json", tmp_path / "control.png"
    args = build_parser().parse_args(
        ["demo", "--problem", "control", "--steps", "30", "--json", str(table), "--plot", str(plot)]
    )
    assert _demo.main(args) == 0
    out = capsys.readouterr().out
    assert "spherical body" in out and "spacecraft" in out
    document = json.loads(table.read_text(encoding="utf-8"))
    (sphere,) = document["sphere"]
    assert abs(sphere["cost_error"] - 1 / (12**2 - 1)) < 1e-6 / 12**2
    assert document["spacecraft"]["attitude_error"] <= 1e-6
    assert len(document["spacecraft"]["u"]) == 30
    assert plot.stat().st_size > 0
