"""`suggest_integrator` from the benchmark's knowledge (no run), its refusal of trajectory
targets beyond a chaotic problem's predictability horizon, and its pilot's cost bound.
The knowledge path runs nothing, and the pilot's runs are replaced by a stand-in whose
error is `h²` (the bound is on the steps it asks for); one test runs a suggestion to check
that it meets its tolerance."""

import math
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import hlw_problem
from lievi import _suggest
from lievi._suggest_knowledge import METHODS

RHO = jnp.array([0.0, 0.0, 0.5])


def _no_run(*args, **kwargs):
    raise AssertionError("the knowledge path must not run anything")


def _top(moments):
    return lievi.heavy_top(jnp.asarray(moments), 1.0, RHO, 1.0, inertia_about="center_of_mass")


def test_a_known_problem_is_answered_without_a_run(monkeypatch):
    monkeypatch.setattr(_suggest, "_final", _no_run)
    body, g0, m0 = hlw_problem()
    for tolerance_on, tolerance in (("attitude", 1e-6), ("energy", 1e-8), ("momentum map", 1e-12)):
        s = lievi.suggest_integrator(
            body, g0, m0, horizon=2e4, tolerance=tolerance, tolerance_on=tolerance_on
        )
        assert s.source == "knowledge"
        assert s.n_steps * s.h == pytest.approx(2e4, rel=1e-12)
        assert 0 < s.predicted_error <= tolerance * (1 + 1e-9)
        assert s.seconds_per_body == min(r["seconds_per_body"] for r in s.table if "h" in r)
        names = {type(m()).__name__ for m in METHODS.values()}
        assert type(s.integrator).__name__ in names
    # The momentum map to 1e-12 over 2e4: only a structure-preserving method keeps it.
    assert s.integrator.is_symmetric()


def test_trajectory_targets_beyond_the_predictability_horizon_are_refused(monkeypatch):
    calls = []
    monkeypatch.setattr(_suggest, "_final", _stand_in(calls))
    g0 = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.1]))
    top = _top((0.6, 0.8, 1.0))  # asymmetric, off-axis gravity: chaotic
    m0 = jnp.array([0.5, 0.3, 1.2])
    with pytest.raises(ValueError, match="chaotic.*predictability horizon"):
        lievi.suggest_integrator(top, g0, m0, horizon=2e4, tolerance=1e-6, tolerance_on="attitude")
    assert not calls  # refused before any run
    # Its invariants can be targets at any horizon, from the table.
    s = lievi.suggest_integrator(top, g0, m0, horizon=2e4, tolerance=1e-6, tolerance_on="energy")
    assert s.source == "knowledge" and 0 < s.predicted_error <= 1e-6 * (1 + 1e-9)
    assert not calls
    # A short horizon's attitude is within reach (the table has no chaotic attitude: a
    # pilot).
    s = lievi.suggest_integrator(top, g0, m0, horizon=20.0, tolerance=1e-6, tolerance_on="attitude")
    assert s.source == "pilot"
    # The integrable Lagrange top's (I₁ = I₂, centre of mass on the axis) at any horizon,
    # from its own class of the table, without a run.
    calls.clear()
    lagrange = _top((0.8, 0.8, 1.0))
    s = lievi.suggest_integrator(
        lagrange, g0, jnp.array([0.3, -0.2, 2.0]), horizon=2e4, tolerance=1e-6,
        tolerance_on="attitude",
    )  # fmt: skip
    assert s.source == "knowledge" and not calls


def _stand_in(calls):
    """`_suggest._final` with the error `h²` on every entry, recording `(h, n_steps)`."""

    def final(system, integrator, g0, m0, h, n_steps):
        calls.append((float(h), int(n_steps), g0.shape[0]))
        batch = g0.shape[0]
        g = jnp.broadcast_to(g0[:, None] + h**2, (batch, 2, *g0.shape[1:]))
        m = jnp.broadcast_to(m0[:, None] + h**2, (batch, 2, *m0.shape[1:]))
        return SimpleNamespace(result=np.zeros(batch, int), g=g, m=m)

    return final


@pytest.mark.parametrize("fraction", [0.05, 0.5])
def test_the_pilot_is_bounded_to_a_fraction_of_the_run(monkeypatch, fraction):
    calls = []
    monkeypatch.setattr(_suggest, "_final", _stand_in(calls))
    body, g0, m0 = hlw_problem()
    horizon, h0 = 1000.0, 0.1
    s = lievi.suggest_integrator(
        body,
        g0,
        m0,
        horizon=horizon,
        tolerance=1e-6,
        candidates=(lievi.DEP(),),  # given candidates: a pilot, not the table
        h0=h0,
        pilot_fraction=fraction,
        batch=2,
    )
    assert s.source == "pilot"
    pilot = [(h, n) for h, n, bodies in calls if bodies == 1]
    assert len(pilot) == 3
    window = pilot[0][0] * pilot[0][1]
    assert all(h * n == pytest.approx(window) for h, n in pilot)
    assert window < horizon
    # 7n steps of one body, at most the fraction of the run's T/h₀ steps (to one step's
    # rounding a level), and the window at least 8 steps of h₀.
    assert sum(n for _, n in pilot) <= max(fraction * horizon / h0, 7 * 8) + 7
    assert window >= 8 * h0 * (1 - 1e-12)
    # The error `h²` grows like t for the symmetric DEP: the step meets `tolerance` at the
    # horizon, not only at the window's end.
    assert s.predicted_error <= 1e-6 * (1 + 1e-9)
    growth = horizon / window
    assert s.h <= math.sqrt(1e-6 / growth) * 1.001


@pytest.mark.parametrize("tolerance", [1e-4, 1e-7])
def test_the_lagrange_top_gets_its_own_method_and_meets_the_tolerance(tolerance):
    """The Lagrange top is its own class: at loose targets the table picks the
    structure-preserving `SymmetricTopSplitting` (the cheapest there in the benchmark),
    and the suggested run meets the attitude tolerance against a DOP853 reference (the
    benchmark's state, T = 20; the table's constants bound its measured errors)."""
    g0 = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.1]))
    m0 = jnp.array([0.3, -0.2, 2.0])
    top = _top((0.8, 0.8, 1.0))
    s = lievi.suggest_integrator(
        top, g0, m0, horizon=20.0, tolerance=tolerance, tolerance_on="attitude"
    )
    assert s.source == "knowledge"
    if tolerance == 1e-4:
        assert isinstance(s.integrator, lievi.SymmetricTopSplitting)
    save = lievi.Save(every=s.n_steps)
    sol = lievi.simulate(top, s.integrator, g0, m0, h=s.h, n_steps=s.n_steps, save=save)
    g_ref, _ = lievi.reference_solution(top, g0, m0, [0.0, 20.0])
    # The rotation angle by its sine, from the antisymmetric part (`arccos` of the trace
    # loses everything below ~1e-8 to rounding).
    R = sol.g[-1].T @ g_ref[-1]
    angle = float(jnp.linalg.norm(R - R.T) / (2 * jnp.sqrt(2.0)))
    assert angle <= tolerance, (type(s.integrator).__name__, s.h, angle)
