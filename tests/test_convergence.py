"""Order of accuracy and long-time behaviour (docs/theory/checks.md; the paper's open question).

The order is fitted by regression of log error on log h against a DOP853 reference
(rtol = atol = 1e-13), as diffrax's order tests do. Both charts are second order: the
answer to the question at the end of the paper's §5 is yes for the exponential chart.
"""

import numpy as np
import pytest

import lievi
from helpers import (
    INTEGRATOR_IDS,
    INTEGRATORS,
    INTEGRATORS_EXP_EXTENDED,
    ROUNDOFF,
    hlw_problem,
    random_generalized_body,
)
from lievi import diagnostics as dg

ORDER_TOLERANCE = 0.1


def observed_order(system, integrator, g0, m0, T, hs):
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, [0.0, T])
    errors = []
    for h in hs:
        sol = lievi.simulate(system, integrator, g0, m0, h=h, n_steps=int(round(T / h)))
        error = max(np.max(np.abs(sol.m[-1] - m_ref[-1])), np.max(np.abs(sol.g[-1] - g_ref[-1])))
        errors.append(error)
    slope = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    return slope, errors


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 8 s
def test_second_order_on_hlw(integrator):
    body, g0, m0 = hlw_problem()
    hs = [0.1 / 2**k for k in range(4)]
    order, errors = observed_order(body, integrator, g0, m0, 2.0, hs)
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 8 s
def test_second_order_on_son(integrator):
    body, g0, m0 = random_generalized_body(np.random.default_rng(4), 4)
    hs = [0.05 / 2**k for k in range(3)]
    order, errors = observed_order(body, integrator, g0, m0, 1.0, hs)
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


def test_order_check_can_fail():
    """Sanity check of the harness: a deliberately first-order map is detected."""

    class Lagging(lievi.DEP):
        def step(self, system, g, m, h):  # advances g with the old momentum's velocity
            g1, m1, info = super().step(system, g, m, h)
            return g @ system.group.exp(h * system.velocity(m)), m1, info

    body, g0, m0 = hlw_problem()
    order, _ = observed_order(body, Lagging(), g0, m0, 2.0, [0.1 / 2**k for k in range(4)])
    assert abs(order - 2) > ORDER_TOLERANCE


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=INTEGRATOR_IDS)
def test_energy_bounded_without_drift_over_1e5_steps(integrator):
    """h = 0.1, T = 1e4: the energy error oscillates with a bounded amplitude."""
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(
        body, integrator, g0, m0, h=0.1, n_steps=100_000, save=lievi.Save(every=10)
    )
    assert sol.result == lievi.RESULTS.successful
    energy = dg.energy(body, sol.g, sol.m)
    error = np.asarray((energy - energy[0]) / energy[0])
    tenth = len(error) // 10
    first, last = np.max(np.abs(error[:tenth])), np.max(np.abs(error[-tenth:]))
    # Bounded: the last tenth's amplitude is the first tenth's, to 1%.
    assert last <= 1.01 * first
    # No linear drift: the fitted trend over the whole run is a tiny fraction of the amplitude.
    slope = np.polyfit(np.asarray(sol.ts), error, 1)[0]
    assert abs(slope) * float(sol.ts[-1]) <= 1e-3 * first
    # Energy error is O(h²) and small.
    assert first <= 1e-3
    # The group element stays on SO(3) to round-off after 1e5 products.
    assert dg.orthogonality_defect(body, sol.g[-1]) <= ROUNDOFF


@pytest.mark.slow
def test_energy_bounded_over_1e6_steps():
    """T = 1e5 at h = 0.1 (exp chart): still bounded, still on the group."""
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(
        body, lievi.DEP(), g0, m0, h=0.1, n_steps=1_000_000, save=lievi.Save(every=100)
    )
    energy = dg.energy(body, sol.g, sol.m)
    error = np.asarray((energy - energy[0]) / energy[0])
    tenth = len(error) // 10
    assert np.max(np.abs(error[-tenth:])) <= 1.01 * np.max(np.abs(error[:tenth]))
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= 10 * ROUNDOFF
    assert dg.orthogonality_defect(body, sol.g[-1]) <= 10 * ROUNDOFF
