"""`Composition`: orders 4, 6 and 8 by regression, symmetry, structure, StepInfo, bad input.

Orders are fitted by regression of log error on log h against the DOP853 reference
(rtol = atol = 1e-13) on the HLW body to T = 2, with step sizes chosen so that the errors
stay well above the reference's own ~1e-13. The final state is computed by a jitted
`fori_loop` whose trip count is traced, so each integrator compiles once for all h.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_generalized_body
from lievi import diagnostics as dg

ORDER_TOLERANCE = 0.2
T = 2.0
# Errors from ~1e-4 down to ~1e-10 (order 4), ~1e-7 down to ~1e-11 (order 6), ~1e-7
# (splitting) or ~1e-9 (DEP) down to ~1e-10 / ~1e-11 (order 8).
STEPS = {4: (10, 20, 40, 80), 6: (5, 7, 10, 14, 20), 8: (3, 4, 5, 6)}


@eqx.filter_jit
def final_state(system, integrator, g0, m0, h, n):
    def body(_, state):
        g, m = state
        g, m, _ = integrator.step(system, g, m, h)
        return g, m

    return jax.lax.fori_loop(0, n, body, (g0, m0))


# Jitted: the system is then traced, as under `simulate`.
step = eqx.filter_jit(lambda integrator, system, g, m, h: integrator.step(system, g, m, h))


@pytest.fixture(scope="module")
def hlw_reference():
    body, g0, m0 = hlw_problem()
    g_ref, m_ref = lievi.reference_solution(body, g0, m0, [0.0, T])
    return body, g0, m0, g_ref[-1], m_ref[-1]


def final_errors(reference, integrator, steps):
    """Max-norm error in `(g, Π)` at T for each number of steps."""
    body, g0, m0, g_ref, m_ref = reference
    errors = []
    for n in steps:
        g, m = final_state(body, integrator, g0, m0, jnp.asarray(T / n), jnp.asarray(n))
        errors.append(max(np.max(np.abs(m - m_ref)), np.max(np.abs(g - g_ref))))
    return errors


def observed_order(reference, integrator, steps):
    errors = final_errors(reference, integrator, steps)
    hs = T / np.asarray(steps, float)
    return np.polyfit(np.log(hs), np.log(errors), 1)[0], errors


CASES = [
    (lievi.DEP(), 4, None),
    (lievi.DEP(), 6, None),
    (lievi.MoserVeselov(), 4, None),
    (lievi.MoserVeselov(), 6, None),
    (lievi.LiePoissonSplitting(), 4, None),
    (lievi.LiePoissonSplitting(), 6, None),
    (lievi.LiePoissonSplitting(), 8, None),
    (lievi.DEP(), 8, None),
]
CASE_IDS = ["dep-4", "dep-6", "mv-4", "mv-6", "splitting-4", "splitting-6", "splitting-8", "dep-8"]
# Larger error constants than the defaults: finer steps (4× those of `STEPS`, 6× at order
# 8) to reach the asymptotic regime (Yoshida's order 8 at 4× the steps still had local
# slopes 7.70, 7.81, 7.87); smaller ones (Sofroniou–Spaletta's): `STEPS`' coarser end, whose
# errors (~4e-8 … 8e-11 at order 6, ~1e-9 … 3e-11 at order 8) stay above the reference's.
COARSER = {6: (5, 7, 10, 14), 8: (2, 3, 4, 5)}
SLOW_CASES = [
    (lievi.DEP(chart="cayley"), 4, "suzuki", tuple(4 * n for n in STEPS[4])),
    (lievi.DEP(chart="cayley"), 6, "yoshida", tuple(4 * n for n in STEPS[6])),
    (lievi.MoserVeselov(), 6, "triple-jump", tuple(4 * n for n in STEPS[6])),
    (lievi.LiePoissonSplitting(), 8, "yoshida", tuple(6 * n for n in STEPS[8])),
    (lievi.DEP(), 8, "triple-jump", tuple(6 * n for n in STEPS[8])),
    (lievi.LiePoissonSplitting(), 6, "sofroniou-spaletta", COARSER[6]),
    (lievi.LiePoissonSplitting(), 8, "sofroniou-spaletta", COARSER[8]),
]
SLOW_IDS = [
    "dep-cayley-4-suzuki",
    "dep-cayley-6-yoshida",
    "mv-6-triple-jump",
    "splitting-8-yoshida",
    "dep-8-triple-jump",
    "splitting-6-sofroniou-spaletta",
    "splitting-8-sofroniou-spaletta",
]


@pytest.mark.parametrize("method, order, scheme", CASES, ids=CASE_IDS)
def test_order(hlw_reference, method, order, scheme):
    integrator = lievi.Composition(method, order, scheme)
    assert integrator.order() == order
    slope, errors = observed_order(hlw_reference, integrator, STEPS[order])
    assert abs(slope - order) <= ORDER_TOLERANCE, (slope, errors)
    # And the composition beats the inner method by far at the same h.
    (base_error,) = final_errors(hlw_reference, method, STEPS[order][-1:])
    assert errors[-1] <= 1e-2 * base_error


@pytest.mark.slow
@pytest.mark.parametrize("method, order, scheme, steps", SLOW_CASES, ids=SLOW_IDS)
def test_order_other_schemes(hlw_reference, method, order, scheme, steps):
    slope, errors = observed_order(hlw_reference, lievi.Composition(method, order, scheme), steps)
    assert abs(slope - order) <= ORDER_TOLERANCE, (slope, errors)


def test_coefficients_are_consistent():
    """Σγ = 1 and the stages are palindromic (the structural facts the order relies on)."""
    from lievi._integrators._composition import SCHEMES

    for (order, scheme), gammas in SCHEMES.items():
        assert abs(sum(gammas) - 1) <= 1e-14, scheme
        np.testing.assert_allclose(gammas, gammas[::-1], rtol=0, atol=1e-15, err_msg=scheme)
        # Σγ³ = 0: the first order condition beyond 2 (HLW §V.3.2); Σγ⁵ = 0 from order 6.
        assert abs(sum(g**3 for g in gammas)) <= 1e-12, scheme
        if order >= 6:
            assert abs(sum(g**5 for g in gammas)) <= 1e-12, scheme


def test_symmetric():
    """`Ψ_{−h} ∘ Ψ_h = id` to round-off: the composition is itself symmetric."""
    body, g0, m0 = hlw_problem()
    integrator = lievi.Composition(lievi.MoserVeselov(), 6)
    g1, m1, _ = step(integrator, body, g0, m0, 0.3)
    g2, m2, _ = step(integrator, body, g1, m1, -0.3)
    assert jnp.max(jnp.abs(m2 - m0)) <= ROUNDOFF
    assert jnp.max(jnp.abs(g2 - g0)) <= ROUNDOFF


def test_step_info_combines_stages():
    """Iterations are summed over the stages, the residual is the largest one."""
    body, g0, m0 = hlw_problem()
    method = lievi.MoserVeselov()
    integrator = lievi.Composition(method, 4)
    _, _, info = step(integrator, body, g0, m0, 0.2)
    g, m, total, largest = g0, m0, 0, 0.0
    for gamma in integrator.coefficients:
        g, m, stage = step(method, body, g, m, gamma * 0.2)
        total += int(stage.iterations)
        largest = max(largest, float(stage.residual))
    assert int(info.iterations) == total > len(integrator.coefficients)
    # Equal up to the last bits (the stages are compiled differently inside the scan).
    assert abs(float(info.residual) - largest) <= 1e-15
    assert info.result == lievi.RESULTS.successful


def test_failure_is_reported():
    """A stage whose Newton solve does not converge makes the whole step fail."""
    body, g0, m0 = hlw_problem()
    integrator = lievi.Composition(lievi.MoserVeselov(max_steps=1), 4)
    _, _, info = step(integrator, body, g0, m0, 0.5)
    assert info.result == lievi.RESULTS.newton_not_converged


def test_structure_over_1000_steps():
    """Casimir, spatial momentum and orthogonality kept to round-off (each stage keeps them)."""
    body, g0, m0 = hlw_problem()
    integrator = lievi.Composition(lievi.MoserVeselov(), 4)
    sol = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=1000)
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.spatial_momentum(body, sol.g, sol.m)) <= ROUNDOFF
    assert dg.orthogonality_defect(body, sol.g[-1]) <= ROUNDOFF


@pytest.mark.slow
@pytest.mark.parametrize("method", [lievi.DEP(), lievi.MoserVeselov()], ids=["dep", "mv"])
def test_casimirs_over_1e4_steps(method):
    body, g0, m0 = hlw_problem()
    integrator = lievi.Composition(method, 6)
    sol = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=10_000, save=lievi.Save(every=10))
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    energy = dg.energy(body, sol.g, sol.m)
    # Order 6 at h = 0.1: the energy error stays tiny and bounded.
    assert float(jnp.max(jnp.abs(energy - energy[0]) / energy[0])) <= 1e-7


@pytest.mark.slow
def test_son_order_4():
    """On SO(4) too (one coarse and one fine step size: ratio 2⁴)."""
    body, g0, m0 = random_generalized_body(np.random.default_rng(1), 4)
    t = 1.0
    g_ref, m_ref = lievi.reference_solution(body, g0, m0, [0.0, t])
    integrator = lievi.Composition(lievi.MoserVeselov(), 4)
    errors = []
    for n in (10, 20, 40):
        g, m = final_state(body, integrator, g0, m0, jnp.asarray(t / n), jnp.asarray(n))
        errors.append(max(np.max(np.abs(m - m_ref[-1])), np.max(np.abs(g - g_ref[-1]))))
    slope = np.polyfit(np.log([t / 10, t / 20, t / 40]), np.log(errors), 1)[0]
    assert abs(slope - 4) <= ORDER_TOLERANCE, (slope, errors)


def test_float32():
    body, g0, m0 = hlw_problem()
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    body32 = lievi.RigidBody(f32(body.inertia))
    integrator = lievi.Composition(lievi.MoserVeselov(), 4)
    sol32 = lievi.simulate(body32, integrator, f32(g0), f32(m0), h=0.1, n_steps=20)
    sol64 = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=20)
    assert sol32.m.dtype == jnp.float32
    assert sol32.result == lievi.RESULTS.successful
    np.testing.assert_allclose(sol32.m[-1], sol64.m[-1], atol=1e-4)


def test_bad_input():
    class NotSymmetric(lievi.DEP):
        def is_symmetric(self):
            return False

    with pytest.raises(ValueError, match="symmetric"):
        lievi.Composition(NotSymmetric(), 4)
    with pytest.raises(ValueError, match="`order` must be 4, 6 or 8"):
        lievi.Composition(lievi.DEP(), 3)
    with pytest.raises(ValueError, match="`order` must be 4, 6 or 8"):
        lievi.Composition(lievi.DEP(), True)
    with pytest.raises(ValueError, match="`scheme`"):
        lievi.Composition(lievi.DEP(), 4, "kahan-li")
    with pytest.raises(ValueError, match="lievi integrator"):
        lievi.Composition(lambda g, m, h: (g, m), 4)
    # A composition is of order 4, 6 or 8, not 2: composing it again is refused.
    with pytest.raises(ValueError, match="order 2"):
        lievi.Composition(lievi.Composition(lievi.DEP(), 4), 6)
    # RK4 is neither symmetric nor of order 2.
    with pytest.raises(ValueError, match="symmetric"):
        lievi.Composition(lievi.RK4(), 4)


@pytest.mark.parametrize("inner", [lievi.MoserVeselov(), lievi.LiePoissonSplitting()])
def test_eager_step_with_concrete_system(inner):
    # An eager step runs the stages in a `lax.scan` that closes over a concrete system:
    # the inner method's input checks must still evaluate (not fail on a tracer).
    body, g0, m0 = hlw_problem()
    g, m, info = lievi.Composition(inner).step(body, g0, m0, 0.1)
    assert int(info.result) == int(lievi.RESULTS.successful)
    np.testing.assert_allclose(np.linalg.norm(m), np.linalg.norm(m0), rtol=1e-12)
