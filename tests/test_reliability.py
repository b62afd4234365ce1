"""Regression tests: no silent wrong result (minimal reproducers → the expected behaviour).

Each test names the cause it guards against. The property-based counterparts (random
bodies, many decades of units) are in `test_properties.py`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import hlw_problem

import lievi

IMPLICIT = {
    "dep-exp": lievi.DEP(chart="exp"),
    "dep-cayley": lievi.DEP(chart="cayley"),
    "moser-veselov": lievi.MoserVeselov(),
    "composition": lievi.Composition(lievi.MoserVeselov(), order=4),
    "preprocessed": lievi.PreprocessedMoserVeselov(order=4),
}


# ---- relative Newton tolerance: the solution does not depend on the units -----------------


@pytest.mark.parametrize("name", list(IMPLICIT))
@pytest.mark.parametrize("c", [1e-13, 1e13])
def test_tolerance_is_relative_scaled_body_gives_same_trajectory(name, c):
    """`(I, Π) → (cI, cΠ)` leaves the attitude unchanged; with an absolute tolerance a
    small-unit body "converged" at the explicit-Euler guess with 0 iterations."""
    integrator = IMPLICIT[name]
    body, g0, m0 = hlw_problem()
    ref = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=20)
    scaled = lievi.simulate(lievi.RigidBody(body.inertia * c), integrator, g0, m0 * c, h=0.1, n_steps=20)
    assert int(scaled.result) == 0
    assert int(scaled.stats["total_newton_iterations"]) == int(ref.stats["total_newton_iterations"])
    np.testing.assert_allclose(scaled.g, ref.g, atol=1e-12)
    np.testing.assert_allclose(scaled.m / c, ref.m, atol=1e-12)


@pytest.mark.parametrize("c", [1e-4, 1e4])
def test_tolerance_is_relative_float32_satellite_units(c):
    body, g0, m0 = hlw_problem()
    f32 = jnp.float32
    inertia, g0, m0 = body.inertia.astype(f32), g0.astype(f32), m0.astype(f32)
    for integrator in (lievi.DEP(), lievi.MoserVeselov()):
        ref = lievi.simulate(lievi.RigidBody(inertia), integrator, g0, m0, h=0.1, n_steps=20)
        scaled = lievi.simulate(lievi.RigidBody(inertia * c), integrator, g0, m0 * c, h=0.1, n_steps=20)
        assert scaled.g.dtype == f32
        np.testing.assert_allclose(scaled.g, ref.g, atol=1e-5)


def test_tolerance_time_rescaling_invariance():
    """`(h, Π) → (h/c, cΠ)`: the same increments, hence the same attitudes."""
    body, g0, m0 = hlw_problem()
    for integrator in (lievi.DEP(), lievi.MoserVeselov()):
        ref = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=20)
        fast = lievi.simulate(body, integrator, g0, m0 * 1e9, h=0.1 / 1e9, n_steps=20)
        np.testing.assert_allclose(fast.g, ref.g, atol=1e-12)
