"""`PreprocessedMoserVeselov`: accuracy, orders 4–10, conservation, autodiff, vmap, bad input.

Problem of Hairer & Vilmart, J. Phys. A 39 (2006) 13225: y₀ = (1.8, 0.4, −0.9), Q₀ = I,
I = (0.6, 0.8, 1.0), and the "water molecule" I = (0.345, 0.653, 1.0). Accuracy: the maximum
momentum error over T = 10 against DOP853 (rtol = atol = 1e-14 requested; scipy uses
2.2e-14), compared with the errors of Hairer–Vilmart's own preprocessed DMV code on the same
problem and step counts (`REFERENCE_ERRORS`, also in `docs/preprocessed_dmv.md`). Orders
are fitted by regression (error in Π and Q at T = 2) with step sizes that keep the errors
between ~1e-4 and ~1e-11, well above the reference's own ~1e-13.
"""

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF
from lievi import diagnostics as dg

ORDER_TOLERANCE = 0.2
Y0 = jnp.array([1.8, 0.4, -0.9])
BODIES = {"hv": jnp.array([0.6, 0.8, 1.0]), "water": jnp.array([0.345, 0.653, 1.0])}
T = 2.0
# Step counts over T = 2 per order (errors ~1e-5 … 2e-12).
STEPS = {4: (40, 56, 80, 112), 6: (40, 56, 80, 112), 8: (12, 16, 20, 28), 10: (10, 12, 16, 20)}
STEPS_WATER = {
    4: (80, 112, 160, 224),
    6: (80, 112, 160, 224),
    8: (24, 32, 40, 56),
    10: (16, 20, 24, 32),
}


@eqx.filter_jit
def prepare(integrator, system, m0, h):
    return integrator.prepare(system, m0, h)


@eqx.filter_jit
def final_state(system, integrator, g0, m0, h, n):
    def body(_, state):
        g, m = state
        g, m, _ = integrator.step(system, g, m, h)
        return g, m

    return jax.lax.fori_loop(0, n, body, (g0, m0))


def observed_order(name, order, steps, t=T):
    body = lievi.RigidBody(BODIES[name])
    g0 = jnp.eye(3)
    g_ref, m_ref = lievi.reference_solution(body, g0, Y0, [0.0, t])
    errors = []
    for n in steps:
        h = jnp.asarray(t / n)
        integrator = prepare(lievi.PreprocessedMoserVeselov(order), body, Y0, h)
        g, m = final_state(body, integrator, g0, Y0, h, jnp.asarray(n))
        errors.append(max(np.max(np.abs(m - m_ref[-1])), np.max(np.abs(g - g_ref[-1]))))
    slope = np.polyfit(np.log(t / np.asarray(steps, float)), np.log(errors), 1)[0]
    return slope, errors


# max |Π error| over T = 10 of Hairer–Vilmart's code (orders 4–10, N = 100 and 200 steps;
# N = 200 at order 10 is round-off) on the body I = (0.6, 0.8, 1.0).
REFERENCE_ERRORS = {
    4: {100: 1.9e-3, 200: 1.1e-4},
    6: {100: 5.8e-6, 200: 8.7e-8},
    8: {100: 9.5e-9, 200: 3.6e-11},
    10: {100: 9.8e-12, 200: 1e-13},
}
T_LONG = 10.0


@functools.lru_cache
def reference_momenta(name, n):
    """DOP853 momenta at the `n + 1` step times over T = 10 (cached across tests)."""
    body = lievi.RigidBody(BODIES[name])
    ts = np.linspace(0.0, T_LONG, n + 1)
    with warnings.catch_warnings():  # scipy raises rtol to 100 ulps itself; that is fine
        warnings.simplefilter("ignore", UserWarning)
        _, m_ref = lievi.reference_solution(body, jnp.eye(3), Y0, ts, rtol=1e-14, atol=1e-14)
    return m_ref


@eqx.filter_jit
def max_error_run(system, integrator, m0, h, n, m_ref):
    """max_k |Π_k − m_ref[k]| over an `n`-step run, preprocessing (`prepare`) included;
    `n` is traced and `m_ref` padded to a fixed length, so each order compiles once."""
    integrator = integrator.prepare(system, m0, h)

    def body(k, state):
        g, m, worst = state
        g, m, _ = integrator.step(system, g, m, h)
        return g, m, jnp.maximum(worst, jnp.max(jnp.abs(m - m_ref[k + 1])))

    state = (jnp.eye(3, dtype=m0.dtype), m0, jnp.zeros((), m0.dtype))
    return jax.lax.fori_loop(0, n, body, state)[2]


def max_momentum_error(name, order, n, padded=801):
    body = lievi.RigidBody(BODIES[name])
    m_ref = np.zeros((padded, 3))
    m_ref[: n + 1] = reference_momenta(name, n)
    integrator = lievi.PreprocessedMoserVeselov(order)
    h = jnp.asarray(T_LONG / n)
    return float(max_error_run(body, integrator, Y0, h, jnp.asarray(n), jnp.asarray(m_ref)))


@pytest.mark.parametrize(
    "order", [4, 6] + [pytest.param(order, marks=pytest.mark.slow) for order in (8, 10)]
)
def test_as_accurate_as_hairer_vilmart(order):
    """Within 2× of Hairer–Vilmart's own errors at N = 100 and 200 (or below 1e-13), and
    the observed order between them within ±0.2 where both are above round-off."""
    errors = {n: max_momentum_error("hv", order, n) for n in (100, 200)}
    for n, error in errors.items():
        assert error <= max(2 * REFERENCE_ERRORS[order][n], 1e-13), (n, errors)
    if errors[200] > 1e-12:
        assert abs(np.log2(errors[100] / errors[200]) - order) <= ORDER_TOLERANCE, errors


@pytest.mark.slow
@pytest.mark.parametrize("order", [4, 6, 8, 10])
def test_water_molecule_errors_fall_with_the_order(order):
    """The flat body at N = 100, 200, 400: within 2× of Hairer–Vilmart's errors (or below
    1e-13), and the order within ±0.2 between the first two counts above round-off."""
    reference = {  # max |Π error| over T = 10 of Hairer–Vilmart's code; 1e-13: round-off
        4: {100: 4.50e-2, 200: 2.58e-3, 400: 1.58e-4},
        6: {100: 3.21e-4, 200: 4.55e-6, 400: 6.95e-8},
        8: {100: 1.55e-6, 200: 5.55e-9, 400: 2.13e-11},
        10: {100: 3.91e-9, 200: 3.45e-12, 400: 1e-13},
    }[order]
    errors = {n: max_momentum_error("water", order, n) for n in reference}
    for n, error in errors.items():
        assert error <= max(2 * reference[n], 1e-13), (n, errors)
    assert abs(np.log2(errors[100] / errors[200]) - order) <= ORDER_TOLERANCE, errors


@pytest.mark.slow
@pytest.mark.parametrize("order", [4, 6, 8, 10])
def test_order(order):
    slope, errors = observed_order("hv", order, STEPS[order])
    assert abs(slope - order) <= ORDER_TOLERANCE, (slope, errors)
    assert min(errors) >= 1e-12  # the fit stays clear of the reference's accuracy


@pytest.mark.slow
@pytest.mark.parametrize("order", [4, 6, 8, 10])
def test_order_water_molecule(order):
    slope, errors = observed_order("water", order, STEPS_WATER[order])
    assert abs(slope - order) <= ORDER_TOLERANCE, (slope, errors)


@pytest.mark.slow
def test_dmv_keeps_energy_exactly():
    """The fact the preprocessing rests on: plain DMV conserves H (and C) to round-off."""
    body = lievi.RigidBody(BODIES["hv"])
    sol = lievi.simulate(body, lievi.MoserVeselov(), jnp.eye(3), Y0, h=0.2, n_steps=200)
    assert dg.relative_drift(dg.energy(body, sol.g, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF


@pytest.mark.slow
def test_unprepared_step_equals_prepared():
    body = lievi.RigidBody(BODIES["water"])
    integrator = lievi.PreprocessedMoserVeselov(6)
    h = jnp.asarray(0.05)
    prepared = prepare(integrator, body, Y0, h)
    g1, m1 = final_state(body, integrator, jnp.eye(3), Y0, h, jnp.asarray(10))
    g2, m2 = final_state(body, prepared, jnp.eye(3), Y0, h, jnp.asarray(10))
    assert jnp.max(jnp.abs(m1 - m2)) <= ROUNDOFF
    assert jnp.max(jnp.abs(g1 - g2)) <= ROUNDOFF


@pytest.mark.extended  # 10 s
def test_structure_over_1000_steps():
    body = lievi.RigidBody(BODIES["hv"])
    integrator = prepare(lievi.PreprocessedMoserVeselov(6), body, Y0, jnp.asarray(0.05))
    sol = lievi.simulate(
        body, integrator, jnp.eye(3), Y0, h=0.05, n_steps=1000, save=lievi.Save(every=10)
    )
    assert sol.result == lievi.RESULTS.successful
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.energy(body, sol.g, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.spatial_momentum(body, sol.g, sol.m)) <= ROUNDOFF
    assert dg.orthogonality_defect(body, sol.g[-1]) <= ROUNDOFF


@pytest.mark.slow
def test_casimirs_over_1e4_steps():
    body = lievi.RigidBody(BODIES["water"])
    integrator = lievi.PreprocessedMoserVeselov(6).prepare(body, Y0, 0.01)
    sol = lievi.simulate(
        body, integrator, jnp.eye(3), Y0, h=0.01, n_steps=10_000, save=lievi.Save(every=10)
    )
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.energy(body, sol.g, sol.m)) <= ROUNDOFF


@pytest.mark.slow
@pytest.mark.parametrize("wrt", ["inertia", "m0"])
def test_gradient_matches_finite_differences(wrt):
    """d(final Π, final Q)/d(inertia or Π₀) through `prepare` (the series) and the Newton
    solves, against central differences."""
    h, n = 0.1, 5

    @jax.jit
    def final(inertia, m0):
        body = lievi.RigidBody(inertia)
        integrator = lievi.PreprocessedMoserVeselov(6).prepare(body, m0, h)
        sol = lievi.simulate(body, integrator, jnp.eye(3), m0, h=h, n_steps=n)
        return jnp.concatenate([sol.m[-1], sol.g[-1].reshape(-1)])

    args = [BODIES["hv"], Y0]
    k = 0 if wrt == "inertia" else 1
    jacobian = jax.jit(jax.jacrev(final, argnums=k))(*args)
    eps = 1e-6
    columns = []
    for i in range(3):
        plus, minus = list(args), list(args)
        plus[k], minus[k] = args[k].at[i].add(eps), args[k].at[i].add(-eps)
        columns.append((final(*plus) - final(*minus)) / (2 * eps))
    assert jnp.all(jnp.isfinite(jacobian))
    np.testing.assert_allclose(jacobian, jnp.stack(columns, axis=1), rtol=1e-6, atol=1e-8)


@pytest.mark.extended  # 10 s
def test_full_inertia_tensor_equals_principal_frame():
    """A rotated body (full tensor `R diag(I) Rᵀ`, momentum `RΠ`, attitude `Q Rᵀ`) gives the
    conjugated trajectory: the modified moments are built from trace invariants."""
    R = lievi.SO3.exp(jnp.array([0.3, -0.7, 0.5]))
    principal = lievi.RigidBody(BODIES["water"])
    tensor = lievi.RigidBody(R @ jnp.diag(BODIES["water"]) @ R.T)
    h, n = jnp.asarray(0.1), 5
    integrator = lievi.PreprocessedMoserVeselov(8)
    g1, m1 = final_state(principal, prepare(integrator, principal, Y0, h), jnp.eye(3), Y0, h, n)
    g2, m2 = final_state(tensor, prepare(integrator, tensor, R @ Y0, h), R.T, R @ Y0, h, n)
    np.testing.assert_allclose(m2, R @ m1, atol=ROUNDOFF)
    np.testing.assert_allclose(g2, g1 @ R.T, atol=ROUNDOFF)


@pytest.mark.slow
def test_symmetric():
    """Stepping with −h undoes a step (α, β are even in h and depend on H, C only)."""
    body = lievi.RigidBody(BODIES["water"])
    integrator = lievi.PreprocessedMoserVeselov(6)
    step = jax.jit(integrator.step)
    h = jnp.asarray(0.2)
    g1, m1, _ = step(body, jnp.eye(3), Y0, h)
    g0, m0, _ = step(body, g1, m1, -h)
    np.testing.assert_allclose(m0, Y0, atol=ROUNDOFF)
    np.testing.assert_allclose(g0, jnp.eye(3), atol=ROUNDOFF)


@pytest.mark.slow
def test_equivalent_moser_veselov_runs_on_the_batched_fast_path():
    """Plain DMV on the modified bodies (`simulate_batch`'s structure-of-arrays path) takes
    the preprocessed method's steps."""
    body = lievi.RigidBody(BODIES["water"])
    integrator = lievi.PreprocessedMoserVeselov(8)
    h, n = 0.05, 20
    m0s = jnp.stack([Y0, 0.5 * Y0, jnp.array([0.1, 1.0, 0.3])])
    bodies, method = eqx.filter_vmap(
        lambda m0: integrator.equivalent_moser_veselov(body, m0, h), out_axes=(0, None)
    )(m0s)
    g0s = jnp.broadcast_to(jnp.eye(3), (3, 3, 3))
    assert lievi.advanced.has_fast_path(bodies, method, system_axis=0)
    batch = lievi.simulate_batch(
        bodies, method, g0s, m0s, h=h, n_steps=n, system_axis=0, save=lievi.Save(every=n)
    )
    for k in range(3):
        prepared = integrator.prepare(body, m0s[k], h)
        sol = lievi.simulate(body, prepared, jnp.eye(3), m0s[k], h=h, n_steps=n)
        np.testing.assert_allclose(batch.m[k, -1], sol.m[-1], atol=ROUNDOFF)
        np.testing.assert_allclose(batch.g[k, -1], sol.g[-1], atol=ROUNDOFF)


@pytest.mark.slow
def test_vmap_over_initial_momenta():
    body = lievi.RigidBody(BODIES["hv"])
    h = jnp.asarray(0.1)
    m0s = jnp.stack([Y0, 0.5 * Y0, jnp.array([0.1, 1.0, 0.3])])

    def run(m0):
        integrator = lievi.PreprocessedMoserVeselov(6).prepare(body, m0, h)
        return final_state(body, integrator, jnp.eye(3), m0, h, jnp.asarray(5))[1]

    batched = jax.jit(jax.vmap(run))(m0s)
    for k in range(3):
        np.testing.assert_allclose(batched[k], run(m0s[k]), atol=ROUNDOFF)


def test_relative_equilibrium():
    """Spin about a principal axis: ẏ = 0, the time shift is undetermined; the attitude is
    still right (the rotation angle absorbs it): the exact solution is a uniform rotation.
    Order 10 at h = 0.05: the truncation error (~(h|Ω|)¹¹ per step) is far below 1e-10."""
    inertia = BODIES["hv"]
    body = lievi.RigidBody(inertia)
    m0 = jnp.array([0.0, 0.0, 1.5])
    h, n = jnp.asarray(0.05), 40
    integrator = prepare(lievi.PreprocessedMoserVeselov(10), body, m0, h)
    g, m = final_state(body, integrator, jnp.eye(3), m0, h, jnp.asarray(n))
    exact = lievi.SO3.exp(jnp.array([0.0, 0.0, 1.5 / inertia[2] * float(h) * n]))
    np.testing.assert_allclose(m, m0, atol=ROUNDOFF)
    np.testing.assert_allclose(g, exact, atol=1e-10)


def test_bad_input():
    with pytest.raises(ValueError, match="`order`"):
        lievi.PreprocessedMoserVeselov(5)
    with pytest.raises(ValueError, match="`method`"):
        lievi.PreprocessedMoserVeselov(6, method=lievi.DEP())
    son = lievi.GeneralizedRigidBody(jnp.array([1.0, 2.0, 3.0, 4.0]))
    with pytest.raises(ValueError, match="RigidBody"):
        lievi.PreprocessedMoserVeselov(6).prepare(son, jnp.zeros(6), 0.1)
    with pytest.raises(ValueError, match="m0"):
        lievi.PreprocessedMoserVeselov(6).prepare(lievi.RigidBody(BODIES["hv"]), jnp.zeros(4), 0.1)
    top = lievi.RigidBody(BODIES["hv"], potential=lievi.UniformGravity(1.0, jnp.array([0, 0, 0.1])))
    with pytest.raises(ValueError, match="potential"):
        lievi.PreprocessedMoserVeselov(6).prepare(top, Y0, 0.1)


@pytest.mark.extended  # 13 s
def test_prepared_for_another_step_size():
    """The series of a prepared integrator belong to one h. `simulate` prepares every run
    for its own h (`init`): a copy prepared for another h runs as one prepared for this h
    (and as the unprepared integrator, whose run is prepared the same way). Its `step`,
    called directly with another h, is an error rather than a silent low-order step."""
    body = lievi.RigidBody(BODIES["hv"])
    integrator = lievi.PreprocessedMoserVeselov(6)
    runs = [
        lievi.simulate(body, method, jnp.eye(3), Y0, h=0.05, n_steps=3)
        for method in (integrator.prepare(body, Y0, 0.1), integrator.prepare(body, Y0, 0.05))
    ]
    runs.append(lievi.simulate(body, integrator, jnp.eye(3), Y0, h=0.05, n_steps=3))
    for sol in runs:
        assert int(sol.result) == int(lievi.RESULTS.successful)
        np.testing.assert_array_equal(sol.m, runs[1].m)
    prepared = integrator.prepare(body, Y0, 0.1)
    with pytest.raises(Exception, match="prepared for another step size"):
        jax.block_until_ready(prepared.step(body, jnp.eye(3), Y0, jnp.asarray(0.05)))


@pytest.mark.slow
def test_float32():
    """The whole pipeline (series, Newton, rotation) runs in float32 and stays close."""
    finals = {}
    for dtype in (jnp.float32, jnp.float64):
        body = lievi.RigidBody(BODIES["hv"].astype(dtype))
        m0, h = Y0.astype(dtype), jnp.asarray(0.05, dtype)
        integrator = lievi.PreprocessedMoserVeselov(6).prepare(body, m0, h)
        sol = lievi.simulate(body, integrator, jnp.eye(3, dtype=dtype), m0, h=h, n_steps=200)
        assert sol.m.dtype == dtype and sol.result == lievi.RESULTS.successful
        finals[dtype] = sol.m[-1]
    np.testing.assert_allclose(finals[jnp.float32], finals[jnp.float64], atol=1e-4)
