"""The RK4 baseline: fourth order, and visibly not structure-preserving (docs/theory/checks.md)."""

import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_generalized_body
from lievi import diagnostics as dg

RK4 = lievi.RK4()
ORDER_TOLERANCE = 0.1


def observed_order(system, g0, m0, T, hs):
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, [0.0, T])
    errors = []
    for h in hs:
        sol = lievi.simulate(system, RK4, g0, m0, h=h, n_steps=int(round(T / h)))
        errors.append(
            max(np.max(np.abs(sol.m[-1] - m_ref[-1])), np.max(np.abs(sol.g[-1] - g_ref[-1])))
        )
    return np.polyfit(np.log(hs), np.log(errors), 1)[0], errors


def test_fourth_order_on_hlw():
    body, g0, m0 = hlw_problem()
    order, errors = observed_order(body, g0, m0, 2.0, [0.2 / 2**k for k in range(3)])
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)


@pytest.mark.slow
def test_fourth_order_on_so4():
    body, g0, m0 = random_generalized_body(np.random.default_rng(4), 4)
    order, errors = observed_order(body, g0, m0, 1.0, [0.1 / 2**k for k in range(3)])
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)


def test_right_invariant_equals_mirrored_left_run():
    """The right run of `(g, μ)` for `l` is the left run of `(gᵀ, −μ)` for `l(−ξ)`: RK4 is
    equivariant under this linear map, so the iterates agree to round-off."""
    body, g0, m0 = hlw_problem()
    right = lievi.LieLagrangian(lievi.SO3, body.lagrangian, side="right")
    left = lievi.LieLagrangian(lievi.SO3, lambda xi: body.lagrangian(-xi))
    a = lievi.simulate(right, RK4, g0, m0, h=0.1, n_steps=20)
    b = lievi.simulate(left, RK4, g0.T, -m0, h=0.1, n_steps=20)
    np.testing.assert_allclose(a.g, jnp.swapaxes(b.g, -1, -2), rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(a.m, -b.m, rtol=0, atol=ROUNDOFF)


def test_drift_over_t_1e4():
    """h = 0.1, T = 1e4 (1e5 steps, ~2 s): RK4 visibly drifts. Energy and Casimir are off
    by > 1e-6 (measured 1.4e-5 and 2.0e-5) and grow linearly; `g` is off SO(3) by > 1e-2
    (measured 2e-2). Every Lie–Poisson method keeps the Casimirs and `gᵀg = I` to ≤ 1e-12
    over runs as long (their tests), and its energy error bounded."""
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, RK4, g0, m0, h=0.1, n_steps=100_000, save=lievi.Save(every=100))
    energy = np.asarray(dg.energy(body, sol.g, sol.m))
    casimir = np.asarray(dg.casimirs(body, sol.m))[:, 0]
    energy_error = np.abs(energy / energy[0] - 1)
    casimir_error = np.abs(casimir / casimir[0] - 1)
    assert energy_error[-1] >= 1e-6 and casimir_error[-1] >= 1e-6
    # Linear growth: the error at T is ≈ 2× the error at T/2 (within 20%).
    half = len(energy) // 2
    assert 1.6 <= energy_error[-1] / energy_error[half] <= 2.4
    assert 1.6 <= casimir_error[-1] / casimir_error[half] <= 2.4
    assert dg.orthogonality_defect(body, sol.g[-1]) >= 1e-2


def test_bad_input():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="`m` must have shape"):
        RK4.step(body, g0, jnp.ones(4), 0.1)
    with pytest.raises(ValueError, match="`g` must have shape"):
        RK4.step(body, jnp.eye(4), m0, 0.1)


def test_float32_run():
    body, g0, m0 = hlw_problem()
    body32 = lievi.RigidBody(body.inertia.astype(jnp.float32))
    sol32 = lievi.simulate(
        body32, RK4, g0.astype(jnp.float32), m0.astype(jnp.float32), h=np.float32(0.1), n_steps=100
    )
    sol64 = lievi.simulate(body, RK4, g0, m0, h=0.1, n_steps=100)
    assert sol32.m.dtype == jnp.float32 and sol32.result == lievi.RESULTS.successful
    np.testing.assert_allclose(sol32.m, sol64.m, rtol=0, atol=1e-4)
