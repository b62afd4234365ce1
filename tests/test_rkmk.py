"""RKMK4, the Lie-group Runge–Kutta method: fourth order in `g` and `m` on either side,
with a potential and with forcing, and `g` on the group to round-off (where the embedded
`RK4` drifts off it)."""

import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_generalized_body
from lievi import diagnostics as dg

RKMK4 = lievi.RKMK4()
ORDER_TOLERANCE = 0.1  # on the slope of log error against log h over a factor 4 in h


def final_errors(system, g0, m0, T, hs, integrator=RKMK4, forcing=None):
    """The final error in `g` and `m` (∞-norm, against DOP853 at 1e-13) for each `h`."""
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, [0.0, T], forcing=forcing)
    errors = []
    for h in hs:
        n = int(round(T / h))
        sol = lievi.simulate(system, integrator, g0, m0, h=h, n_steps=n, forcing=forcing)
        errors.append(
            max(np.max(np.abs(sol.m[-1] - m_ref[-1])), np.max(np.abs(sol.g[-1] - g_ref[-1])))
        )
    return errors


def observed_order(system, g0, m0, T, hs, forcing=None):
    """The slope of log error against log h, and the errors."""
    errors = final_errors(system, g0, m0, T, hs, forcing=forcing)
    return np.polyfit(np.log(hs), np.log(errors), 1)[0], errors


HS = [0.2 / 2**k for k in range(3)]


@pytest.mark.parametrize("side", ["left", "right"])
def test_fourth_order_and_more_accurate_than_embedded_rk4(side):
    """HLW's free rigid body, T = 2: order 4.0 ± 0.1 on both sides, and at equal step more
    accurate than classical RK4 in the matrix embedding (measured 11×)."""
    body, g0, m0 = hlw_problem()
    system = body if side == "left" else lievi.LieLagrangian(lievi.SO3, body.lagrangian, side=side)
    order, errors = observed_order(system, g0, m0, 2.0, HS)
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)
    (rk4_error,) = final_errors(system, g0, m0, 2.0, HS[:1], lievi.RK4())
    assert errors[0] < rk4_error / 5, (errors[0], rk4_error)


def test_fourth_order_heavy_top_with_control():
    """A heavy top (a potential) driven by a time-varying control torque: order 4."""
    top = lievi.heavy_top(jnp.array([2.0, 1.0, 2 / 3]), 1.0, jnp.array([0.1, 0.05, 0.4]), 1.0)
    g0 = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.1]))
    m0 = jnp.array([0.4, -0.2, 1.1])
    forcing = lievi.ForceLaw(lambda t, g, m, args: 0.1 * jnp.array([jnp.sin(t), 0.0, jnp.cos(t)]))
    order, errors = observed_order(top, g0, m0, 2.0, HS, forcing=forcing)
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)


def test_stays_on_the_group_where_rk4_drifts():
    """Heavy top, h = 0.1, 1e4 steps: ‖gᵀg − I‖ stays at round-off (the attitude moves only
    by exponentials), while the embedded RK4's drifts by orders of magnitude more."""
    top = lievi.heavy_top(jnp.array([2.0, 1.0, 2 / 3]), 1.0, jnp.array([0.1, 0.05, 0.4]), 1.0)
    g0, m0 = jnp.eye(3), jnp.array([0.4, -0.2, 1.1])
    kwargs = dict(h=0.1, n_steps=10_000, save_every=10_000)
    sol = lievi.simulate(top, RKMK4, g0, m0, **kwargs)
    assert int(sol.result) == lievi.RESULTS.successful
    assert dg.orthogonality_defect(top, sol.g[-1]) <= ROUNDOFF
    embedded = lievi.simulate(top, lievi.RK4(), g0, m0, **kwargs)
    assert dg.orthogonality_defect(top, embedded.g[-1]) >= 1e3 * ROUNDOFF


@pytest.mark.slow
def test_fourth_order_on_so4_and_se3():
    body, g0, m0 = random_generalized_body(np.random.default_rng(4), 4)
    order, errors = observed_order(body, g0, m0, 1.0, [0.1 / 2**k for k in range(3)])
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)
    se3 = lievi.RigidBodySE3(
        jnp.array([1.0, 1.5, 2.0]), 2.0, potential=lievi.UniformGravitySE3(2.0)
    )
    g0 = lievi.SE3.exp(jnp.array([0.2, -0.1, 0.3, 0.5, 0.0, -0.4]))
    m0 = jnp.array([0.5, -0.3, 0.8, 1.0, 0.2, -0.5])
    order, errors = observed_order(se3, g0, m0, 1.0, [0.1 / 2**k for k in range(3)])
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)


def test_float32_stays_on_the_group():
    body, g0, m0 = hlw_problem()
    body32 = lievi.RigidBody(body.inertia.astype(jnp.float32))
    sol = lievi.simulate(
        body32, RKMK4, g0.astype(jnp.float32), m0.astype(jnp.float32), h=0.05, n_steps=2000
    )
    assert sol.m.dtype == jnp.float32 and int(sol.result) == lievi.RESULTS.successful
    # 64 ulps of float32 (the library's membership tolerance for float32).
    assert dg.orthogonality_defect(body32, sol.g[-1]) <= 64 * np.finfo(np.float32).eps


def test_bad_input():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="`m` must have shape"):
        RKMK4.step(body, g0, jnp.ones(4), 0.1)
    with pytest.raises(ValueError, match="`g` must have shape"):
        RKMK4.step(body, jnp.eye(4), m0, 0.1)
