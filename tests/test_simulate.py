"""`simulate`: Newton behaviour, failure reporting and argument checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import INTEGRATOR_IDS, INTEGRATORS, hlw_problem


@pytest.mark.extended  # 11–13 s each
@pytest.mark.parametrize("integrator", INTEGRATORS, ids=INTEGRATOR_IDS)
def test_newton_converges_fast_for_moderate_steps(integrator):
    """Residual ≤ 1e-13 within ≤ 5 iterations whenever h·|Ω| ≤ 0.5."""
    body, g0, _ = hlw_problem()
    rng = np.random.default_rng(0)
    momenta = rng.normal(size=(64, 3))
    tight = lievi.DEP(chart=integrator.chart, rtol=1e-14, atol=1e-14)

    def solve(m):
        omega = jnp.linalg.norm(body.velocity(m))
        h = 0.5 / omega  # h·|Ω| = 0.5, the edge of the promised regime
        _, info = tight.solve_increment(body, m, h)
        return info

    info = jax.vmap(solve)(jnp.asarray(momenta))
    assert jnp.all(info.converged)
    assert jnp.max(info.residual) <= 1e-13
    assert jnp.max(info.iterations) <= 5


def test_step_too_large_is_reported_not_returned():
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, lievi.DEP(chart="exp"), g0, m0, h=10.0, n_steps=5, throw=False)
    assert sol.result != lievi.RESULTS.successful
    assert sol.stats["failed_step"] == 0
    # Nothing after the failure can be mistaken for a number.
    assert jnp.all(jnp.isnan(sol.m[1:])) and jnp.all(jnp.isnan(sol.g[1:]))
    with pytest.raises(Exception, match="Reduce the step size"):
        lievi.simulate(body, lievi.DEP(chart="exp"), g0, m0, h=10.0, n_steps=5)


def test_newton_not_converging_is_reported():
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, lievi.DEP(max_steps=1), g0, m0, h=0.1, n_steps=5, throw=False)
    assert sol.result == lievi.RESULTS.newton_not_converged
    with pytest.raises(Exception, match="max_steps"):
        lievi.simulate(body, lievi.DEP(max_steps=1), g0, m0, h=0.1, n_steps=5)


@pytest.mark.extended  # 9 s
def test_failure_in_a_batch_is_per_body():
    """Under vmap with throw=False a NaN body fails alone; the others carry on."""
    body, g0, m0 = hlw_problem()
    momenta = jnp.stack([m0, m0.at[1].set(jnp.nan), 2 * m0])

    def run(m):
        return lievi.simulate(body, lievi.DEP(), g0, m, h=0.1, n_steps=10, throw=False)

    sol = jax.vmap(run)(momenta)
    # A NaN initial momentum is a bad input, reported as such per body under vmap.
    assert list(sol.result) == [0, lievi.RESULTS.invalid_input, 0]
    assert jnp.all(jnp.isfinite(sol.m[0])) and jnp.all(jnp.isfinite(sol.m[2]))


@pytest.mark.extended  # 10 s
def test_save_every_and_times():
    body, g0, m0 = hlw_problem()
    full = lievi.simulate(body, lievi.DEP(), g0, m0, h=0.1, n_steps=12)
    sparse = lievi.simulate(
        body, lievi.DEP(), g0, m0, h=0.1, n_steps=12, save=lievi.Save(every=4), t0=1.0
    )
    assert sparse.m.shape == (4, 3) and sparse.g.shape == (4, 3, 3)
    np.testing.assert_allclose(sparse.m, full.m[::4], rtol=0, atol=1e-14)
    np.testing.assert_allclose(sparse.ts, 1.0 + 0.4 * jnp.arange(4), rtol=1e-14)
    assert sparse.stats["newton_iterations"].shape == (3,)
    assert int(sparse.stats["total_newton_iterations"]) == int(
        full.stats["total_newton_iterations"]
    )


def test_float32_run():
    """float32 is a supported mode: converges, keeps |Π| to a few ulps, tracks float64."""
    body, g0, m0 = hlw_problem()
    body32 = lievi.RigidBody(body.inertia.astype(jnp.float32))
    sol32 = lievi.simulate(
        body32,
        lievi.DEP(),
        g0.astype(jnp.float32),
        m0.astype(jnp.float32),
        h=np.float32(0.1),
        n_steps=200,
    )
    sol64 = lievi.simulate(body, lievi.DEP(), g0, m0, h=0.1, n_steps=200)
    assert sol32.m.dtype == jnp.float32
    assert sol32.result == lievi.RESULTS.successful
    casimir = lievi.diagnostics.casimirs(body32, sol32.m)
    assert lievi.diagnostics.relative_drift(casimir) <= 1e-5
    np.testing.assert_allclose(sol32.m, sol64.m, rtol=0, atol=1e-4)


@pytest.mark.extended  # 18 s each
@pytest.mark.parametrize("integrator", [lievi.DEP(), lievi.MoserVeselov()], ids=["dep", "mv"])
def test_mixed_precision_promotes(integrator):
    """A float64 system with a float32 state (or the reverse) runs in float64, NumPy's
    promotion, on the generic and the batched fast path alike, and equals the float64 run."""
    body, g0, m0 = hlw_problem()
    body32 = lievi.RigidBody(body.inertia.astype(jnp.float32))
    g32, m32 = g0.astype(jnp.float32), m0.astype(jnp.float32)
    reference = lievi.simulate(
        body, integrator, g32.astype(float), m32.astype(float), h=0.1, n_steps=10
    )
    for system, g, m in [(body, g32, m32), (body32, g0, m0)]:
        sol = lievi.simulate(system, integrator, g, m, h=0.1, n_steps=10)
        assert sol.m.dtype == sol.g.dtype == jnp.float64
        if system is body:
            np.testing.assert_allclose(sol.m, reference.m, rtol=0, atol=1e-14)
    batch = lievi.simulate_batch(
        body, integrator, g32[None], m32[None], h=0.1, n_steps=10, save=lievi.Save(every=10)
    )
    assert batch.m.dtype == jnp.float64
    np.testing.assert_allclose(batch.m[0, -1], reference.m[-1], rtol=0, atol=1e-13)


# ---- bad input --------------------------------------------------------------------------


def _run(**overrides):
    body, g0, m0 = hlw_problem()
    kwargs = dict(system=body, integrator=lievi.DEP(), g0=g0, m0=m0, h=0.1, n_steps=3)
    kwargs.update(overrides)
    return lievi.simulate(**kwargs)


@pytest.mark.parametrize(
    "overrides, match",
    [
        (dict(m0=jnp.zeros(4)), "`m0` must have shape"),
        (dict(g0=jnp.eye(4)), "`g0` must have shape"),
        (dict(h=0.0), "`h` must be > 0"),
        (dict(h=-0.1), "`h` must be > 0"),
        (dict(h=float("nan")), "`h` contains NaN"),
        (dict(h=jnp.ones(2)), "`h` must be a scalar"),
        (dict(n_steps=0), "`n_steps` must be an integer ≥ 1"),
        (dict(n_steps=2.5), "`n_steps` must be an integer"),
        (dict(save=lievi.Save(every=2)), "`save.every` .* must divide `n_steps`"),
        (dict(m0=jnp.array([1.0, jnp.nan, 0.0])), "`m0` contains NaN"),
        (dict(g0=jnp.eye(3) * 1.01), "`g0` is not in the group"),
        (dict(g0=jnp.diag(jnp.array([1.0, 1.0, -1.0]))), "`g0` is not in the group"),
        (dict(m0=None), "exactly one of `m0`"),
    ],
)
def test_bad_simulate_arguments(overrides, match):
    with pytest.raises(ValueError, match=match):
        _run(**overrides)


@pytest.mark.parametrize(
    "inertia, match",
    [
        (jnp.array([1.0, 2.0]), "`inertia` must be principal moments of shape"),
        (jnp.array([1.0, -2.0, 1.0]), "`inertia` must be positive definite"),
        (jnp.array([1.0, 0.0, 1.0]), "`inertia` must be positive definite"),
        (
            jnp.array([[1.0, 2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
            "`inertia` must be symmetric",
        ),
        (
            jnp.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
            "`inertia` must be positive definite",
        ),
        (jnp.array([1.0, jnp.nan, 1.0]), "`inertia` contains NaN"),
    ],
)
def test_bad_inertia(inertia, match):
    with pytest.raises(ValueError, match=match):
        lievi.RigidBody(inertia)


def test_bad_generalized_body():
    with pytest.raises(ValueError, match="Λᵢ \\+ Λⱼ > 0"):
        lievi.GeneralizedRigidBody(jnp.array([1.0, -1.0, 0.5, 2.0]))
    with pytest.raises(ValueError, match="`Lambda` must be a vector"):
        lievi.GeneralizedRigidBody(jnp.ones((3, 3)))


def test_bad_integrator_settings():
    with pytest.raises(ValueError, match="`chart` must be one of"):
        lievi.DEP(chart="quaternion")
    with pytest.raises(ValueError, match="`max_steps`"):
        lievi.DEP(max_steps=0)
    with pytest.raises(ValueError, match="`side` must be one of"):
        lievi.LieLagrangian(lievi.SO3, lambda x: x @ x, side="middle")


@pytest.mark.extended  # 10 s
def test_simulate_under_outer_jit_and_vmap():
    """Eager checks must not break when `simulate` is traced with concrete captured values."""
    body, g0, m0 = hlw_problem()

    def final(m):
        return lievi.simulate(body, lievi.DEP(), g0, m, h=0.1, n_steps=10, throw=False).m[-1]

    expected = final(m0)
    np.testing.assert_allclose(jax.jit(final)(m0), expected, rtol=0, atol=1e-14)
    batched = jax.jit(jax.vmap(final))(jnp.stack([m0, 2 * m0]))
    np.testing.assert_allclose(batched[0], expected, rtol=0, atol=1e-14)
