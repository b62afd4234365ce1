"""Regression tests: no silent wrong result (minimal reproducers → the expected behaviour).

Each test names the cause it guards against. The property-based counterparts (random
bodies, many decades of units) are in `test_properties.py`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import GenericPreprocessed, hlw_problem

IMPLICIT = {
    "dep-exp": lievi.DEP(chart="exp"),
    "dep-cayley": lievi.DEP(chart="cayley"),
    "moser-veselov": lievi.MoserVeselov(),
    "composition": lievi.Composition(lievi.MoserVeselov(), order=4),
    "preprocessed": lievi.PreprocessedMoserVeselov(order=4),
}


# ---- relative Newton tolerance: the solution does not depend on the units -----------------


# The small units of the Cayley chart, the composition and the preprocessed method are
# extended (4–5 s each).
@pytest.mark.parametrize(
    "c, name",
    [
        pytest.param(
            c,
            name,
            marks=pytest.mark.extended
            if c < 1 and name in ("dep-cayley", "composition", "preprocessed")
            else (),
        )
        for c in (1e-13, 1e13)
        for name in IMPLICIT
    ],
)
def test_tolerance_is_relative_scaled_body_gives_same_trajectory(name, c):
    """`(I, Π) → (cI, cΠ)` leaves the attitude unchanged; with an absolute tolerance a
    small-unit body "converged" at the explicit-Euler guess with 0 iterations."""
    integrator = IMPLICIT[name]
    body, g0, m0 = hlw_problem()
    # n_steps = 4 as in test_properties.py: the compiled runs are shared.
    ref = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=4)
    scaled = lievi.simulate(
        lievi.RigidBody(body.inertia * c), integrator, g0, m0 * c, h=0.1, n_steps=4
    )
    assert int(scaled.result) == 0
    assert int(scaled.stats["total_newton_iterations"]) == int(ref.stats["total_newton_iterations"])
    np.testing.assert_allclose(scaled.g, ref.g, atol=1e-12)
    np.testing.assert_allclose(scaled.m / c, ref.m, atol=1e-12)


@pytest.mark.extended  # 13 s
@pytest.mark.parametrize("c", [1e-4])
def test_tolerance_is_relative_float32_satellite_units(c):
    body, g0, m0 = hlw_problem()
    f32 = jnp.float32
    inertia, g0, m0 = body.inertia.astype(f32), g0.astype(f32), m0.astype(f32)
    for integrator in (lievi.DEP(), lievi.MoserVeselov()):
        ref = lievi.simulate(lievi.RigidBody(inertia), integrator, g0, m0, h=0.1, n_steps=4)
        scaled = lievi.simulate(
            lievi.RigidBody(inertia * c), integrator, g0, m0 * c, h=0.1, n_steps=4
        )
        assert scaled.g.dtype == f32
        np.testing.assert_allclose(scaled.g, ref.g, atol=1e-5)


def test_tolerance_time_rescaling_invariance():
    """`(h, Π) → (h/c, cΠ)`: the same increments, hence the same attitudes."""
    body, g0, m0 = hlw_problem()
    for integrator in (lievi.DEP(), lievi.MoserVeselov()):
        ref = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=4)
        fast = lievi.simulate(body, integrator, g0, m0 * 1e9, h=0.1 / 1e9, n_steps=4)
        np.testing.assert_allclose(fast.g, ref.g, atol=1e-12)


# ---- traced inputs are validated per body (invalid_input), never result = 0 --------------------


def _hlw_batch(inertias):
    _, g0, m0 = hlw_problem()
    B = len(inertias)
    bodies = jax.vmap(lievi.RigidBody)(jnp.asarray(inertias))
    return bodies, jnp.broadcast_to(g0, (B, 3, 3)), jnp.broadcast_to(m0, (B, 3))


@pytest.mark.parametrize(
    "integrator, fast",
    [
        (lievi.RK4(), True),
        (lievi.DEP(), False),
        (lievi.PreprocessedMoserVeselov(), True),
        (GenericPreprocessed(), True),
    ],
    # The batch kernel; the one-body kernel under `jax.vmap`; a kernel with per-body
    # constants from `m0`; a method without a kernel, its own step under `jax.vmap`.
    ids=["rk4-fast", "dep-one-body", "preprocessed-fast", "preprocessed-generic"],
)
def test_vmapped_bodies_with_bad_inertia_fail_alone(integrator, fast):
    """The README idiom `jax.vmap(lievi.RigidBody)(inertias)` skips the eager check; the
    body with inertia (−1, 1, 1) must still fail, and only it."""
    bodies, g0, m0 = _hlw_batch([[2.0, 1.0, 2 / 3], [-1.0, 1.0, 1.0], [0.0, 1.0, 1.0]])
    sol = lievi.simulate_batch(
        bodies,
        integrator,
        g0,
        m0,
        h=0.1,
        n_steps=2,
        system_axis=0,
        save=lievi.Save(every=2),
        tuning=lievi.advanced.Tuning(fast=fast),
        throw=False,
    )
    invalid = lievi.RESULTS.invalid_input
    assert [int(r) for r in sol.result] == [0, invalid, invalid]
    assert np.all(np.isfinite(np.asarray(sol.m[0])))


def test_throw_inside_jit_is_not_dropped():
    """Per-input traced checks are in `test_properties.py`; here: with `throw=True` inside
    the caller's `jit`, a failure raises even when only `g`/`m` are used."""
    _, g0, m0 = hlw_problem()

    @jax.jit
    def attitude(inertia):
        return lievi.simulate(lievi.RigidBody(inertia), lievi.DEP(), g0, m0, h=0.1, n_steps=2).g

    with pytest.raises(Exception, match="input is invalid"):
        attitude(jnp.array([-1.0, 1.0, 1.0])).block_until_ready()


class _NaNAttitude(lievi.RK4):
    """A method whose step returns a finite momentum but a NaN attitude."""

    def step(self, system, g, m, h):
        g_next, m_next, info = super().step(system, g, m, h)
        return g_next * jnp.nan, m_next, info


def test_nonfinite_attitude_is_reported():
    """Every step's `g` is checked, not only `m` (a NaN attitude gave result = 0)."""
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, _NaNAttitude(), g0, m0, h=0.1, n_steps=2, throw=False)
    assert int(sol.result) == lievi.RESULTS.nonfinite


# ---- SOn.log near a half-turn; non-rotations -------------------------------------------------


def test_son2_log_of_half_turn_is_exact():
    g = -jnp.eye(2)
    x = jax.jit(lievi.SOn(2).log)(g)
    np.testing.assert_allclose(lievi.SOn(2).exp(x), g, atol=1e-15)
    assert abs(abs(float(x[0])) - np.pi) < 1e-15


@pytest.mark.extended  # 10 s
def test_son4_near_half_turns_exact():
    """60 random SO(4) rotations with one plane within 1e-16…1e-4 of π: exp(log g) = g."""
    rng = np.random.default_rng(0)
    group = lievi.SOn(4)
    gs = []
    for _ in range(60):
        q = np.linalg.qr(rng.normal(size=(4, 4)))[0]
        a, b = np.pi - 10.0 ** rng.uniform(-16, -4), rng.uniform(0, 3)
        R = np.eye(4)
        for p, t in ((0, a), (2, b)):
            R[p, p] = R[p + 1, p + 1] = np.cos(t)
            R[p + 1, p], R[p, p + 1] = np.sin(t), -np.sin(t)
        gs.append(q @ R @ q.T)
    gs = jnp.asarray(np.stack(gs))
    x = jax.jit(group.log)(gs)
    error = np.max(np.abs(np.asarray(group.exp(x) - gs)), axis=(1, 2))
    assert np.all(error <= 256 * 4 * np.finfo(float).eps)


@pytest.mark.extended  # 12 s
def test_log_checked_rejects_non_rotations():
    x = jnp.array([0.3, -0.2, 0.1])
    gs = jnp.stack(
        [jnp.diag(jnp.array([1.0, 1.0, -1.0])), 2 * jnp.eye(3), -jnp.eye(3), lievi.SO3.exp(x)]
    )
    for group in (lievi.SO3, lievi.SOn(3)):
        out = np.asarray(jax.jit(group.log_checked)(gs))
        assert np.all(np.isnan(out[:3]))
        np.testing.assert_allclose(out[3], x, atol=1e-15)


# ---- the step bound ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "integrator, h",
    [(lievi.DEP(chart="cayley"), 10.0), (lievi.LiePoissonSplitting(), 100.0), (lievi.RK4(), 6.0)],
    ids=["dep-cayley", "splitting", "rk4"],
)
def test_huge_steps_are_step_too_large(integrator, h):
    body, g0, m0 = hlw_problem()  # |Ω| ≈ 1.36
    sol = lievi.simulate(body, integrator, g0, m0, h=h, n_steps=2, throw=False)
    assert int(sol.result) == lievi.RESULTS.step_too_large
    assert int(sol.stats["failed_step"]) == 0


def test_huge_steps_batched_both_paths_same_code():
    bodies, g0, m0 = _hlw_batch([[2.0, 1.0, 2 / 3]] * 2)
    for integrator in (lievi.RK4(),):
        codes = [
            lievi.simulate_batch(
                bodies,
                integrator,
                g0,
                m0,
                h=jnp.array([0.1, 6.0]),
                n_steps=2,
                system_axis=0,
                save=lievi.Save(every=2),
                tuning=lievi.advanced.Tuning(fast=fast),
                throw=False,
            ).result
            for fast in (True, False)
        ]
        assert [int(c) for c in codes[0]] == [0, lievi.RESULTS.step_too_large]
        np.testing.assert_array_equal(codes[0], codes[1])


def test_composition_bound_is_the_longest_stage():
    composition = lievi.Composition(lievi.DEP(), order=4)
    gamma = max(abs(c) for c in composition.coefficients)
    assert composition.step_bound() == pytest.approx(np.pi / gamma)


# ---- Moser–Veselov: one branch on both paths ---------------------------------------------------


def test_moser_veselov_branch_rule_same_on_both_paths():
    """I, m0, h from a reproducer: the generic and the batched solve had landed on two
    different roots, both 'successful'. Both roots are outside the branch rule's set."""
    body = lievi.RigidBody(jnp.array([1.925, 0.546, 0.599]))
    m0 = jnp.array([0.710, 0.304, -0.624])
    for h, expected in ((1.617, lievi.RESULTS.step_too_large), (0.5, 0)):
        single = lievi.simulate(
            body, lievi.MoserVeselov(), jnp.eye(3), m0, h=h, n_steps=1, throw=False
        )
        batch = lievi.simulate_batch(
            body,
            lievi.MoserVeselov(),
            jnp.eye(3)[None],
            m0[None],
            h=h,
            n_steps=1,
            throw=False,
            save=lievi.Save(every=1),
        )
        assert int(single.result) == int(batch.result[0]) == expected
        if expected == 0:
            np.testing.assert_allclose(batch.m[0], single.m, atol=1e-14)


# ---- prepared PreprocessedMoserVeselov -----------------------------------------------------------


@pytest.mark.extended  # 16 s
def test_prepared_preprocessed_rejects_another_trajectory_and_bad_h():
    """`simulate` prepares each run for its own trajectory (`init`): a copy prepared for
    another one runs as the unprepared method. Its `step` on a state of another
    trajectory (other energy and Casimir) is `invalid_input`, not a silent low-order step."""
    body, g0, m0 = hlw_problem()
    method = lievi.PreprocessedMoserVeselov(order=4)
    prepared = method.prepare(body, m0, 0.1)
    other = lievi.simulate(body, prepared, g0, 1.5 * m0, h=0.1, n_steps=2, throw=False)
    fresh = lievi.simulate(body, method, g0, 1.5 * m0, h=0.1, n_steps=2, throw=False)
    assert int(other.result) == 0
    np.testing.assert_array_equal(other.m, fresh.m)
    _, _, info = prepared.step(body, g0, m0, jnp.asarray(0.1))
    assert int(info.result) == 0
    _, _, info = prepared.step(body, g0, 1.5 * m0, jnp.asarray(0.1))
    assert int(info.result) == lievi.RESULTS.invalid_input
    for h in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="`h`"):
            method.prepare(body, m0, h)


# ---- clear errors ----------------------------------------------------------------------------------


def test_clear_errors_for_bad_arguments():
    body, g0, m0 = hlw_problem()
    run = lievi.simulate
    with pytest.raises(ValueError, match="`h` must be a real number"):
        run(body, lievi.DEP(), g0, m0, h="0.1", n_steps=2)
    with pytest.raises(ValueError, match="`h` must be a real number"):
        run(body, lievi.DEP(), g0, m0, h=0.1 + 0j, n_steps=2)
    with pytest.raises(ValueError, match="`h` must be a real number"):
        run(body, lievi.DEP(), g0, m0, h=True, n_steps=2)
    with pytest.raises(ValueError, match="subnormal"):
        run(body, lievi.DEP(), g0, m0, h=1e-310, n_steps=2)
    with pytest.raises(ValueError, match="`t0`"):
        run(body, lievi.DEP(), g0, m0, h=0.1, n_steps=2, t0=float("nan"))
    with pytest.raises(ValueError, match="`inertia` must hold real numbers"):
        lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]) + 0j)
    with pytest.raises(ValueError, match="`inertia` must hold real numbers"):
        lievi.RigidBody(jnp.array([True, True, True]))
    with pytest.raises(ValueError, match="`l` must be a callable"):
        lievi.LieLagrangian(lievi.SO3, None)
    # lists work like arrays
    sol = run(body, lievi.DEP(), np.eye(3).tolist(), [float(v) for v in m0], h=0.1, n_steps=2)
    assert int(sol.result) == 0
    # NumPy integers work like ints
    assert lievi.DEP(max_steps=np.int64(5)).max_steps == 5
    assert lievi.MoserVeselov(max_steps=np.int64(5)).max_steps == 5


def test_g1_outside_the_chart_blames_g1():
    body, g0, _ = hlw_problem()
    half_turn = jnp.diag(jnp.array([1.0, -1.0, -1.0]))
    with pytest.raises(ValueError, match="`g1`"):
        lievi.simulate(body, lievi.DEP(chart="cayley"), g0, g1=half_turn, h=0.1, n_steps=2)


def test_clear_errors_for_batches():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="empty"):
        lievi.simulate_batch(
            body,
            lievi.DEP(),
            jnp.zeros((0, 3, 3)),
            jnp.zeros((0, 3)),
            h=0.1,
            n_steps=2,
            save=lievi.Save(every=2),
        )
    with pytest.raises(ValueError, match="`save` must be a `lievi.Save`"):
        lievi.simulate_batch(body, lievi.DEP(), g0[None], m0[None], h=0.1, n_steps=2, save="gm")
    with pytest.raises(ValueError, match="`devices` is empty"):
        lievi.shard_batch(g0[None], devices=[])


def test_so3_dexpinv_singular_at_two_pi_is_not_finite():
    x = jnp.array([2 * np.pi, 0.0, 0.0])
    assert not np.all(np.isfinite(np.asarray(lievi.SO3.dexpinv(x))))
    assert np.all(np.isfinite(np.asarray(lievi.SO3.dexpinv(jnp.array([3.0, 0.0, 0.0])))))


@pytest.mark.extended  # 8 s
def test_overridden_step_is_run_on_every_path():
    """A subclass that overrides `step` runs its own step, not its parent's kernel: one
    body, `jax.vmap(simulate)` and `simulate_batch` (the fast path used to run the parent's
    kernel and silently return the parent's iterates)."""

    class Damped(lievi.DEP):
        def step(self, system, g, m, h):
            g1, m1, info = super().step(system, g, m, h)
            return g1, 0.5 * m1, info

    body, g0, m0 = hlw_problem()
    one = lievi.simulate(body, Damped(), g0, m0, h=0.1, n_steps=3)
    # DEP's momentum update is a rotation (|Π| kept to round-off): each step halves |Π|.
    norms = jnp.linalg.norm(one.m, axis=-1)
    np.testing.assert_allclose(norms, jnp.linalg.norm(m0) * 0.5 ** jnp.arange(4), rtol=1e-12)
    batch = lievi.simulate_batch(
        body,
        Damped(),
        jnp.stack([g0, g0]),
        jnp.stack([m0, m0]),
        h=0.1,
        n_steps=3,
        save=lievi.Save(every=1),
    )
    vmapped = jax.vmap(lambda g, m: lievi.simulate(body, Damped(), g, m, h=0.1, n_steps=3).m)(
        jnp.stack([g0, g0]), jnp.stack([m0, m0])
    )
    for m in (batch.m[0], vmapped[0]):
        np.testing.assert_allclose(m, one.m, rtol=1e-12, atol=1e-14)
