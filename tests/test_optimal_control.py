"""`lievi.solve_optimal_control`: rest-to-rest reorientation through the forced
variational integrator, against the closed form of a spherical body.

For `J = jI` the rest-to-rest problem of least `∫|u|²` is the eigenaxis manoeuvre,
`u(t) = (jθ_f/T²)(6 − 12t/T) a`, `J* = 12 j² θ_f² / T³`, and the discrete optimum of
`Σ_k h|u_k|²` over `N` held steps costs exactly `J*(1 + 1/(N² − 1))` (the derivation is in
docs/optimal-control.md). Tolerances (float64): the discrete optimum's cost matches
`J*(1 + 1/(N² − 1))` to 1e-9 relative (observed ~2e-12); the terminal conditions are met to
1e-12; the control stays on the eigenaxis to 1e-9 (observed ~3e-12), from a random start
off it. Each new `N` compiles the solver anew (about 25 s on a loaded CPU): the default
suite solves one problem size, N = 8; the convergence study is `slow`.
"""

import json

import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi._cli import build_parser, control, problems
from lievi._cli import main as cli_main

N = 8  # the default suite's problem size (one compilation, shared by its tests)
THETA, AXIS, T = problems.CONTROL_THETA, problems.CONTROL_AXIS, problems.CONTROL_T


def solve_sphere(n, j=1.0, **kwargs):
    sphere = lievi.RigidBody(jnp.full(3, j))
    u0 = jnp.asarray(0.1 * np.random.default_rng(n).normal(size=(n, 3)))  # off the axis
    target = (lievi.SO3.exp(THETA * AXIS), jnp.zeros(3))
    return lievi.solve_optimal_control(
        sphere, lievi.DEP(), jnp.eye(3), jnp.zeros(3), target, n, T / n, u0=u0, **kwargs
    )


@pytest.mark.extended  # 13 s
def test_sphere_rest_to_rest_matches_the_closed_form():
    r = solve_sphere(N)
    assert isinstance(r, lievi.OptimalControlSolution)
    assert r.converged and r.constraint_violation <= 1e-12
    assert 1 <= r.iterations <= 15 and r.inner_iterations >= r.iterations
    optimum = 12 * THETA**2 / T**3
    assert r.cost == pytest.approx(optimum * (1 + 1 / (N**2 - 1)), rel=1e-9)
    u = r.controls
    assert u.shape == (N, 3)
    assert float(jnp.max(jnp.abs(u - (u @ AXIS)[:, None] * AXIS))) < 1e-9  # eigenaxis
    # The profile: the closed form at the step midpoints, to O(h²).
    profile = float(jnp.max(jnp.abs(u - problems.closed_form_control(1.0, N))))
    assert profile < 1 / N**2 * (6 * THETA / T**2)
    # The trajectory it drives: at rest at the target.
    sol = r.solution
    assert int(sol.result) == 0 and sol.g.shape == (N + 1, 3, 3)
    np.testing.assert_allclose(sol.g[-1], lievi.SO3.exp(THETA * AXIS), atol=1e-11)
    np.testing.assert_allclose(sol.m[-1], 0.0, atol=1e-11)
    assert r.multipliers.shape == (6,)


@pytest.mark.extended  # 24 s
def test_unconverged_solve_is_reported():
    """One multiplier update (same size, same compilation) leaves the O(1/ρ) defect."""
    r = solve_sphere(N, max_iterations=1)
    assert not r.converged and r.iterations == 1
    assert 1e-12 < r.constraint_violation < 1e-1


def test_cli_sphere_optimum():
    """The control demo's helper (it calls `solve_optimal_control`)."""
    r = control.sphere_optimum(N)
    assert r["defect"] < 1e-12 and r["off_axis"] < 1e-9
    assert abs(r["cost_error"] - 1 / (N**2 - 1)) < 1e-9
    assert r["profile_error"] < 1 / N**2


def test_bad_arguments():
    sphere = lievi.RigidBody(jnp.ones(3))
    target = (jnp.eye(3), jnp.zeros(3))
    args = (sphere, lievi.DEP(), jnp.eye(3), jnp.zeros(3))
    with pytest.raises(ValueError, match="n_steps"):
        lievi.solve_optimal_control(*args, target, 0, 0.1)
    with pytest.raises(ValueError, match="target"):
        lievi.solve_optimal_control(*args, jnp.eye(3), 4, 0.1)
    with pytest.raises(ValueError, match="u0"):
        lievi.solve_optimal_control(*args, target, 4, 0.1, u0=jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match="max_iterations"):
        lievi.solve_optimal_control(*args, target, 4, 0.1, max_iterations=0)


def test_control_demo_rejects_a_step_size(capsys):
    """`h = T/N` in the control demo: `--h` is refused with a message naming `--steps`."""
    with pytest.raises(SystemExit) as exit_:
        cli_main(["demo", "--problem", "control", "--h", "0.1"])
    assert exit_.value.code == 2
    assert "--steps" in capsys.readouterr().err


@pytest.mark.slow
def test_sphere_discrete_optimum_converges_to_the_closed_form():
    ns = [16, 32, 64, 128]
    results = [control.sphere_optimum(n) for n in ns]
    cost_errors = [r["cost_error"] for r in results]
    for n, error in zip(ns, cost_errors):
        assert abs(error - 1 / (n**2 - 1)) < 1e-9, (n, error)
    order = -np.polyfit(np.log(ns), np.log(cost_errors), 1)[0]
    assert abs(order - 2) < 0.05, (order, cost_errors)
    assert cost_errors[-1] <= 1e-4, cost_errors
    profile_errors = [r["profile_error"] for r in results]
    assert profile_errors[-1] <= 1e-4, profile_errors
    assert max(r["off_axis"] for r in results) < 1e-9  # eigenaxis
    assert max(r["defect"] for r in results) < 1e-12  # at rest at the target


@pytest.mark.slow
def test_free_final_momentum():
    """`target = (g_f, None)`: the cheapest way to the attitude, not at rest."""
    sphere = lievi.RigidBody(jnp.ones(3))
    g_f = lievi.SO3.exp(THETA * AXIS)
    r = lievi.solve_optimal_control(
        sphere, lievi.DEP(), jnp.eye(3), jnp.zeros(3), (g_f, None), 16, T / 16
    )
    assert r.converged and r.multipliers.shape == (3,)
    np.testing.assert_allclose(r.solution.g[-1], g_f, atol=1e-11)
    assert r.cost < 12 * THETA**2 / T**3  # cheaper than arriving at rest


@pytest.mark.slow
def test_asymmetric_spacecraft_reaches_the_target():
    r = control.spacecraft_manoeuvre(60)  # re-simulated with throw=True
    assert r["attitude_error"] <= 1e-6, r["attitude_error"]
    assert r["final_momentum"] <= 1e-6, r["final_momentum"]
    # The gyroscopic coupling moves the optimum off the eigenaxis (unlike the sphere's).
    assert r["off_axis_share"] > 1e-2, r["off_axis_share"]
    u = r["u"]
    assert float(jnp.max(jnp.abs(u - (u @ AXIS)[:, None] * AXIS))) > 1e-2


@pytest.mark.slow
def test_control_demo(tmp_path, capsys, monkeypatch):
    """`python -m lievi demo --problem control` end to end (small N), JSON and plot."""
    pytest.importorskip("matplotlib")
    monkeypatch.setattr(control, "SPHERE_STEPS", (12,))
    table, plot = tmp_path / "control.json", tmp_path / "control.png"
    args = build_parser().parse_args(
        ["demo", "--problem", "control", "--steps", "30", "--json", str(table), "--plot", str(plot)]
    )
    assert control.main(args) == 0
    out = capsys.readouterr().out
    assert "spherical body" in out and "spacecraft" in out
    document = json.loads(table.read_text(encoding="utf-8"))
    (sphere,) = document["sphere"]
    assert abs(sphere["cost_error"] - 1 / (12**2 - 1)) < 1e-9
    assert document["spacecraft"]["attitude_error"] <= 1e-6
    assert len(document["spacecraft"]["u"]) == 30
    assert plot.stat().st_size > 0
