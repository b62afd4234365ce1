"""`suggest_integrator`: the suggested method and step reach the target (checked against
the DOP853 reference), the cheapest candidate is the one suggested, bad input is refused."""

import numpy as np
import pytest

import lievi
from helpers import hlw_problem

HORIZON = 4.0


@pytest.fixture(scope="module")
def problem():
    body, g0, m0 = hlw_problem()
    g_ref, _ = lievi.reference_solution(body, g0, m0, [0.0, HORIZON])
    return body, g0, m0, np.asarray(g_ref[-1])


@pytest.mark.parametrize(
    "tolerance",
    [
        pytest.param(1e-4, marks=pytest.mark.slow),
        pytest.param(1e-8, marks=pytest.mark.extended),  # 30 s
    ],
)
def test_suggested_step_reaches_the_tolerance(problem, tolerance):
    body, g0, m0, g_ref = problem
    candidates = (lievi.DEP(), lievi.Composition(lievi.DEP(), 4), lievi.RKMK4())
    suggestion = lievi.suggest_integrator(
        body, g0, m0, horizon=HORIZON, tolerance=tolerance, candidates=candidates, batch=16
    )
    assert suggestion.n_steps * suggestion.h == pytest.approx(HORIZON, rel=1e-12)
    rows = [r for r in suggestion.table if "failed" not in r]
    assert len(rows) == 3
    # The suggestion is the cheapest row, and each row's estimate is at most the tolerance.
    assert suggestion.seconds_per_body == min(r["seconds_per_body"] for r in rows)
    assert all(r["predicted_error"] <= tolerance * (1 + 1e-9) for r in rows)
    # The estimate holds: the run at the suggested step is within 3× the tolerance (the
    # pilot's Richardson estimate, not a bound; the reference is good to ~1e-12).
    solution = lievi.simulate(
        body, suggestion.integrator, g0, m0, h=suggestion.h, n_steps=suggestion.n_steps
    )
    error = np.linalg.norm(np.asarray(solution.g[-1]) - g_ref)
    assert error <= 3 * tolerance, (error, suggestion.table)
    # A higher-order method needs fewer steps for the tight target.
    steps = {r["name"]: r["n_steps"] for r in rows}
    if tolerance < 1e-6:
        assert steps["Composition (order 4)"] < steps["DEP (order 2)"]


def test_bad_input(problem):
    body, g0, m0, _ = problem
    for kwargs, match in (
        ({"horizon": 1.0, "tolerance": 0.0}, "tolerance"),
        ({"horizon": -1.0, "tolerance": 1e-6}, "horizon"),
        ({"horizon": 1.0, "tolerance": 1e-6, "batch": 0}, "batch"),
    ):
        with pytest.raises(ValueError, match=match):
            lievi.suggest_integrator(body, g0, m0, **kwargs)
