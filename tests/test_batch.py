"""`simulate_batch`: batched results equal per-body `simulate` to round-off; the fast
structure-of-arrays path equals the generic one; failures are per body; sharding."""

import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, ROUNDOFF_F32, random_rotation
from lievi._groups._charts import as_chart
from lievi._kernels import _explicit_adjoints, _explicit_primal, _so3_equations, _soa

CHARTS = ("exp", "cayley")
# Every integrator with a fast path.
FAST = {
    "dep-exp": lievi.DEP(chart="exp"),
    "dep-cayley": lievi.DEP(chart="cayley"),
    "moser-veselov": lievi.MoserVeselov(),
    "splitting": lievi.LiePoissonSplitting(),
    "rk4": lievi.RK4(),
}
BATCH, STEPS, SAVE_EVERY = 24, 20, 5


def random_batch(rng, batch, dtype=jnp.float64):
    inertia = jnp.asarray(rng.uniform(0.5, 2.0, size=(batch, 3)), dtype)
    g0 = jnp.stack([random_rotation(rng, 3) for _ in range(batch)]).astype(dtype)
    m0 = jnp.asarray(rng.normal(size=(batch, 3)), dtype)
    h = jnp.asarray(rng.uniform(0.05, 0.3, size=batch), dtype)
    return jax.vmap(lievi.RigidBody)(inertia), g0, m0, h


@pytest.fixture(scope="module")
def problem():
    return random_batch(np.random.default_rng(5), BATCH)


@pytest.fixture(
    scope="module",
    # The exp chart's checks are extended (8 s and 10 s); the other integrators stay.
    params=[
        pytest.param(name, marks=pytest.mark.extended) if name == "dep-exp" else name
        for name in FAST
    ],
)
def runs(request, problem):
    """Fast path and generic path (vmap of simulate) on the same batch."""
    bodies, g0, m0, h = problem
    dep = FAST[request.param]
    assert lievi.advanced.has_fast_path(bodies, dep, system_axis=0)
    kwargs = dict(h=h, n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY), system_axis=0)
    fast = lievi.simulate_batch(bodies, dep, g0, m0, **kwargs)
    generic = lievi.simulate_batch(
        bodies, dep, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    return dep, fast, generic


def test_fast_equals_generic(runs):
    _, fast, generic = runs
    assert fast.g.shape == generic.g.shape == (BATCH, STEPS // SAVE_EVERY + 1, 3, 3)
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_array_equal(generic.result, 0)
    np.testing.assert_allclose(fast.ts, generic.ts, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.g, generic.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.m, generic.m, rtol=0, atol=ROUNDOFF)
    # Converged to the integrator's tolerance 64 ulps·(1 + ‖Π‖_∞) at every step.
    bound = 64 * np.finfo(np.float64).eps * (1 + np.abs(fast.m).max(axis=(1, 2)))
    assert np.all(fast.stats["residual"] <= bound[:, None])
    np.testing.assert_array_equal(fast.stats["failed_step"], -1)


def test_batched_equals_per_body(runs, problem):
    """The batch (both paths) equals `simulate` called on each body alone."""
    dep, fast, generic = runs
    bodies, g0, m0, h = problem
    for b in (0, 7, BATCH - 1):
        body = lievi.RigidBody(bodies.inertia[b])
        single = lievi.simulate(
            body, dep, g0[b], m0[b], h=h[b], n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY)
        )
        np.testing.assert_allclose(generic.m[b], single.m, rtol=0, atol=ROUNDOFF)
        np.testing.assert_allclose(fast.m[b], single.m, rtol=0, atol=ROUNDOFF)
        np.testing.assert_allclose(fast.g[b], single.g, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("chart", CHARTS + ("moser-veselov",))
@pytest.mark.parametrize(
    "scale", [0.0, 1e-3, 3.1] + [pytest.param(x, marks=pytest.mark.slow) for x in (1e-9, 0.5, 2.0)]
)
def test_closed_form_jacobian(chart, scale):
    """The hand-written residual and 3×3 Jacobian equal `jacfwd` of the generic residual
    (`DEP`'s, or `MoserVeselov`'s), at θ = 0, tiny θ and up to θ = 3.1 (just below π, the
    exp chart's limit)."""
    rng = np.random.default_rng(int(scale * 100))
    inertia, h = jnp.asarray(rng.uniform(0.5, 2.0, 3)), 0.2
    Pi = jnp.asarray(rng.normal(size=3))
    direction = rng.normal(size=3)
    xi = jnp.asarray(scale * direction / np.linalg.norm(direction))
    body = lievi.RigidBody(inertia)
    dinv = body.group.dexpinv if chart == "exp" else body.group.dcayinv

    def residual(x):
        if chart == "moser-veselov":
            eye, X = jnp.eye(3), body.group.hat(x)
            return body.legendre(x) / h - body.group.vee(
                (eye - X / 2) @ body.group.hat(Pi) @ (eye + X / 2)
            )
        return dinv(x).T @ body.legendre(x / h) - Pi

    equation = (
        _so3_equations.MoserVeselovEquation()
        if chart == "moser-veselov"
        else _so3_equations.DEPEquation(as_chart(chart))
    )
    r, J = equation.residual(tuple(xi), tuple(Pi), tuple(inertia / h), True)
    scale_r = 1 + np.abs(residual(xi)).max()
    np.testing.assert_allclose(np.array(r), residual(xi), rtol=0, atol=ROUNDOFF * scale_r)
    np.testing.assert_allclose(
        np.array(J), jax.jacfwd(residual)(xi), rtol=0, atol=ROUNDOFF * 10 / h
    )


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_sincos(dtype):
    """The splitting's polynomial sin/cos: within one ulp of the exact values (numpy in
    float64 on the rounded argument) for angles up to 1e4, both signs, and at 0, ±π/4,
    the quadrant boundaries."""
    rng = np.random.default_rng(0)
    x = np.concatenate(
        [
            rng.uniform(-1e4, 1e4, 4000),
            rng.uniform(-4, 4, 4000),
            np.pi / 4 * np.arange(-8, 9),
            [0.0, -0.0, 1e-30],
        ]
    )
    x = jnp.asarray(x, dtype)
    s, c = jax.jit(_explicit_primal.sincos)(x)
    exact = np.asarray(x, np.float64)
    eps = np.finfo(dtype).eps
    np.testing.assert_allclose(np.asarray(s, np.float64), np.sin(exact), rtol=0, atol=eps)
    np.testing.assert_allclose(np.asarray(c, np.float64), np.cos(exact), rtol=0, atol=eps)


def test_float32(problem):
    """float32 is first class: the fast path matches the generic float32 run to float32
    round-off, keeps the Casimir |Π| to round-off and stays within 1e-4 of float64."""
    bodies, g0, m0, h = problem
    bodies32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), bodies)
    args32 = (g0.astype(jnp.float32), m0.astype(jnp.float32))
    dep = lievi.DEP(chart="exp")
    kwargs = dict(n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY), system_axis=0)
    fast = lievi.simulate_batch(bodies32, dep, *args32, h=h.astype(jnp.float32), **kwargs)
    generic = lievi.simulate_batch(
        bodies32,
        dep,
        *args32,
        h=h.astype(jnp.float32),
        tuning=lievi.advanced.Tuning(fast=False),
        **kwargs,
    )
    exact = lievi.simulate_batch(bodies, dep, g0, m0, h=h, **kwargs)
    assert fast.m.dtype == jnp.float32 and fast.g.dtype == jnp.float32
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_allclose(fast.m, generic.m, rtol=0, atol=ROUNDOFF_F32)
    np.testing.assert_allclose(fast.m, exact.m, rtol=0, atol=ROUNDOFF_F32)
    norms = np.linalg.norm(np.asarray(fast.m, np.float64), axis=-1)
    np.testing.assert_allclose(
        norms,
        np.broadcast_to(norms[:, :1], norms.shape),
        rtol=10 * STEPS * np.finfo(np.float32).eps,
    )


@pytest.mark.slow
def test_one_fixed_iteration_then_tail(problem):
    """With one fixed Newton iteration the convergence tail finishes the job: same iterates."""
    bodies, g0, m0, h = problem
    dep = lievi.DEP(chart="exp")
    kwargs = dict(h=h, n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY), system_axis=0)
    one = lievi.simulate_batch(
        bodies, dep, g0, m0, tuning=lievi.advanced.Tuning(fixed_iterations=1), **kwargs
    )
    generic = lievi.simulate_batch(
        bodies, dep, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    np.testing.assert_allclose(one.m, generic.m, rtol=0, atol=ROUNDOFF)
    assert np.all(one.stats["newton_iterations"] >= 2)  # the tail ran


@pytest.mark.parametrize(
    "chart",
    [
        pytest.param("exp", marks=pytest.mark.extended),  # 11 s
        pytest.param("cayley", marks=pytest.mark.slow),
    ],
)
def test_failures_are_per_body(chart):
    """One body with a far too large step fails; the others carry on, equal to the
    generic path; the failed body is NaN after its failed step; throw=True raises."""
    rng = np.random.default_rng(1)
    bodies, g0, m0, _ = random_batch(rng, 6)
    h = jnp.full(6, 0.1).at[2].set(40.0)
    dep = lievi.DEP(chart=chart, max_steps=6)
    kwargs = dict(h=h, n_steps=8, save=lievi.Save(), system_axis=0, throw=False)
    fast = lievi.simulate_batch(bodies, dep, g0, m0, **kwargs)
    generic = lievi.simulate_batch(
        bodies, dep, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    ok = np.arange(6) != 2
    assert fast.result[2] != lievi.RESULTS.successful
    assert fast.result[2] == generic.result[2]
    assert fast.stats["failed_step"][2] == generic.stats["failed_step"][2] >= 0
    np.testing.assert_array_equal(fast.result[ok], 0)
    np.testing.assert_allclose(fast.m[ok], generic.m[ok], rtol=0, atol=ROUNDOFF)
    k = int(fast.stats["failed_step"][2])
    assert np.all(np.isnan(fast.m[2, k + 1 :])) and np.all(np.isfinite(fast.m[2, : k + 1]))
    with pytest.raises(Exception, match="a body failed"):
        lievi.simulate_batch(bodies, dep, g0, m0, **{**kwargs, "throw": True})
    # Inside the caller's `jit`, with only `m` used, the check is not dropped either.
    only_m = jax.jit(
        lambda m0: lievi.simulate_batch(bodies, dep, g0, m0, **{**kwargs, "throw": True}).m
    )
    with pytest.raises(Exception, match="a body failed"):
        only_m(m0).block_until_ready()


@pytest.mark.extended  # 16 s
def test_moser_veselov_scalar_solve_at_large_steps():
    """The fast Moser–Veselov step solves a scalar quartic first and falls back to Newton
    in `x` where that has not converged (from the explicit-Euler guess where it is worse);
    at steps h|Ω| up to ≈ 3, where four scalar iterations leave many bodies unconverged,
    every body the generic solver integrates is integrated by the fast path too, to the
    same iterates."""
    rng = np.random.default_rng(11)
    bodies, g0, m0, _ = random_batch(rng, 64)
    h = jnp.asarray(rng.uniform(0.2, 0.6, 64))
    A = tuple(bodies.inertia[:, i] / h for i in range(3))
    Pi = tuple(m0[:, i] for i in range(3))
    x = _so3_equations._moser_veselov_by_scalar_newton(Pi, A, 4)
    residual = _soa.max_abs(_so3_equations._residual_moser_veselov(x, Pi, A, False)[0])
    assert np.sum(~(residual <= 64 * np.finfo(np.float64).eps * (1 + _soa.max_abs(Pi)))) >= 5

    kwargs = dict(h=h, n_steps=10, save=lievi.Save(every=10), system_axis=0, throw=False)
    mv = lievi.MoserVeselov()
    fast = lievi.simulate_batch(bodies, mv, g0, m0, **kwargs)
    generic = lievi.simulate_batch(
        bodies, mv, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    ok = np.asarray(generic.result) == 0
    assert ok.sum() >= 32
    np.testing.assert_array_equal(np.asarray(fast.result)[ok], 0)
    np.testing.assert_allclose(fast.m[ok], generic.m[ok], rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.g[ok], generic.g[ok], rtol=0, atol=ROUNDOFF)


@pytest.mark.extended  # 9 s
def test_shared_system_and_save_options(problem):
    _, g0, m0, _ = problem
    body = lievi.RigidBody(jnp.array([2.0, 1.0, 2 / 3]))
    dep = lievi.DEP()
    final = lievi.simulate_batch(
        body, dep, g0, m0, h=0.1, n_steps=STEPS, save=lievi.Save(g=False, stats=False, every=STEPS)
    )
    assert final.g is None and final.m.shape == (BATCH, 2, 3)
    assert "newton_iterations" not in final.stats
    assert final.stats["total_newton_iterations"].shape == (BATCH,)
    single = lievi.simulate(
        body, dep, g0[3], m0[3], h=0.1, n_steps=STEPS, save=lievi.Save(every=STEPS)
    )
    np.testing.assert_allclose(final.m[3], single.m, rtol=0, atol=ROUNDOFF)
    assert lievi.advanced.has_fast_path(body, dep)
    assert not lievi.advanced.has_fast_path(
        lievi.RigidBody(jnp.diag(jnp.array([2.0, 1.0, 0.5]))), dep
    )
    # One initial element for every body broadcasts.
    shared = lievi.simulate_batch(
        body,
        dep,
        jnp.eye(3),
        m0,
        h=0.1,
        n_steps=STEPS,
        save=lievi.Save(g=False, stats=False, every=STEPS),
    )
    broadcast = jnp.broadcast_to(jnp.eye(3), (BATCH, 3, 3))
    full = lievi.simulate_batch(
        body,
        dep,
        broadcast,
        m0,
        h=0.1,
        n_steps=STEPS,
        save=lievi.Save(g=False, stats=False, every=STEPS),
    )
    np.testing.assert_array_equal(shared.m, full.m)
    # `lievi.Save` is the option the names stand for: the same fields, the same values.
    as_object = lievi.simulate_batch(
        body, dep, g0, m0, h=0.1, n_steps=STEPS, save=lievi.Save(g=False, stats=False, every=STEPS)
    )
    assert as_object.g is None and "newton_iterations" not in as_object.stats
    np.testing.assert_array_equal(as_object.m, final.m)
    with pytest.raises(ValueError, match="`Save.g` must be True or False"):
        lievi.Save(g="yes")


@pytest.mark.slow
def test_full_tensor_uses_generic_path(problem):
    """No fast path for a full inertia tensor: the vmap path runs and equals `simulate`."""
    _, g0, m0, _ = problem
    q = np.asarray(random_rotation(np.random.default_rng(3), 3))
    body = lievi.RigidBody(jnp.asarray(q @ np.diag([2.0, 1.0, 0.7]) @ q.T))
    sol = lievi.simulate_batch(
        body, lievi.DEP(), g0[:3], m0[:3], h=0.1, n_steps=4, save=lievi.Save(every=4)
    )
    single = lievi.simulate(
        body, lievi.DEP(), g0[1], m0[1], h=0.1, n_steps=4, save=lievi.Save(every=4)
    )
    np.testing.assert_allclose(sol.m[1], single.m, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(g0=jnp.ones((4, 3))), "`g0` must have shape"),
        (dict(m0=jnp.zeros((5, 3))), "same batch size"),
        (dict(h=jnp.ones(5)), "`h` must be a scalar or have shape"),
        (dict(h=-0.1), "`h` must be > 0"),
        (dict(save=("g", "energy")), "`save` may only contain"),
        (dict(system_axis=1), "`system_axis`"),
        (dict(save=lievi.Save(every=3)), "must divide"),
        (dict(g0=2 * jnp.broadcast_to(jnp.eye(3), (4, 3, 3))), r"`g0\[0\]` is not in the group"),
        (dict(system_axis=0), "leading axis 4"),
    ],
)
def test_bad_input(change, match):
    kwargs = dict(g0=jnp.broadcast_to(jnp.eye(3), (4, 3, 3)), m0=jnp.ones((4, 3)), h=0.1, n_steps=4)
    kwargs.update(change)
    body = lievi.RigidBody(jnp.array([2.0, 1.0, 0.5]))
    g0, m0 = kwargs.pop("g0"), kwargs.pop("m0")
    with pytest.raises(ValueError, match=match):
        lievi.simulate_batch(body, lievi.DEP(), g0, m0, **kwargs)


_SHARDED = """
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np
import lievi
assert len(jax.devices()) == 4, jax.devices()
rng = np.random.default_rng(0)
B = 16
inertia = jnp.asarray(rng.uniform(0.5, 2.0, (B, 3)))
m0 = jnp.asarray(rng.normal(size=(B, 3)))
g0 = jnp.broadcast_to(jnp.eye(3), (B, 3, 3))
h = jnp.asarray(rng.uniform(0.05, 0.2, B))
for fast in (True,):
    args = (jax.vmap(lievi.RigidBody)(inertia), g0, m0, h)
    run = lambda bodies, g0, m0, h: lievi.simulate_batch(
        bodies, lievi.DEP(), g0, m0, h=h, n_steps=10, save=lievi.Save(every=5), system_axis=0,
        tuning=lievi.advanced.Tuning(fast=fast))
    plain = run(*args)
    sharded_args = lievi.shard_batch(args)
    assert len(sharded_args[2].sharding.device_set) == 4
    sharded = run(*sharded_args)
    assert len(sharded.m.sharding.device_set) == 4, sharded.m.sharding
    # Still split over the devices (not gathered onto each by the failure check).
    assert not sharded.m.sharding.is_fully_replicated, sharded.m.sharding
    assert not sharded.g.sharding.is_fully_replicated, sharded.g.sharding
    # Equal to round-off, not bitwise: XLA compiles the per-device shapes (4 bodies) with
    # different vectorisation than the whole batch (16).
    np.testing.assert_allclose(np.asarray(sharded.m), np.asarray(plain.m), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(sharded.g), np.asarray(plain.g), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(np.asarray(sharded.result), np.asarray(plain.result))
print("SHARDED OK")
"""


def test_repeated_call_traces_nothing_of_the_system():
    """A second eager `simulate_batch` call with the same system traces neither its
    potential nor its energy (the shape test of `system_axis`'s inference is cached; it
    was traced again at every call, about 7 ms); a batch of systems built with `jax.vmap`
    is still told apart from one system."""
    traced = []

    def potential(g):
        traced.append(1)
        return 0.1 * g[2, 2]

    body = lievi.RigidBody(jnp.array([2.0, 1.0, 2 / 3]), potential=potential)
    m0 = jnp.asarray(np.random.default_rng(0).normal(size=(4, 3)))

    def run(system, **kwargs):
        return lievi.simulate_batch(system, lievi.DEP(), jnp.eye(3), m0, h=0.1, n_steps=5, **kwargs)

    first = run(body)
    assert traced
    traced.clear()
    second = run(body)
    assert not traced
    np.testing.assert_array_equal(first.m, second.m)
    # The same structure with a leading axis of four: a batch of systems, each body its own.
    free = lievi.RigidBody(jnp.array([2.0, 1.0, 2 / 3]))
    systems = jax.vmap(lambda s: lievi.RigidBody(jnp.array([2.0, 1.0, s])))(
        jnp.array([0.5, 2 / 3, 0.7, 0.8])
    )
    shared, batched = run(free), run(systems)
    np.testing.assert_allclose(batched.m[1], shared.m[1], rtol=0, atol=ROUNDOFF)
    assert not np.allclose(batched.m[0], shared.m[0])


def test_batch_of_systems_with_a_function_potential():
    """A parameter sweep built with `equinox.filter_vmap` keeps a potential given as a
    Python function (`jax.vmap` cannot return one): `simulate_batch` maps the systems'
    arrays only (`AbstractLieSystem.batch_axes`), each body as `simulate` alone, to
    round-off, with and without saving every step (the eager blocks and the traced
    scan); this raised "not a valid JAX type"."""

    def potential(g):
        return 0.1 * g[2, 2]

    moments = jnp.array([0.5, 2 / 3, 0.7, 0.8])
    systems = eqx.filter_vmap(
        lambda s: lievi.RigidBody(jnp.array([2.0, 1.0, s]), potential=potential)
    )(moments)
    m0 = jnp.asarray(np.random.default_rng(1).normal(size=(4, 3)))
    dep = lievi.DEP()
    batched = lievi.simulate_batch(
        systems, dep, jnp.eye(3), m0, h=0.1, n_steps=6, save=lievi.Save(every=2)
    )
    traced = jax.jit(
        lambda m0: lievi.simulate_batch(
            systems, dep, jnp.eye(3), m0, h=0.1, n_steps=6, save=lievi.Save(every=6)
        )
    )(m0)
    for i, s in enumerate(moments):
        body = lievi.RigidBody(jnp.array([2.0, 1.0, s]), potential=potential)
        alone = lievi.simulate(
            body, dep, jnp.eye(3), m0[i], h=0.1, n_steps=6, save=lievi.Save(every=2)
        )
        np.testing.assert_allclose(batched.m[i], alone.m, rtol=0, atol=ROUNDOFF)
        np.testing.assert_allclose(traced.m[i, -1], alone.m[-1], rtol=0, atol=ROUNDOFF)


@pytest.mark.extended  # 13 s
def test_sharded_equals_unsharded():
    """On 4 (forced host) CPU devices the sharded batch equals the unsharded one."""
    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu"
    )
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_SHARDED)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert "SHARDED OK" in done.stdout, done.stdout + done.stderr


# Every kernel's gradients against the generic path run by default in
# tests/test_kernel_parity.py; these longer runs are under -m slow.
@pytest.mark.slow
@pytest.mark.parametrize("name", ["dep-exp", "dep-cayley", "moser-veselov", "splitting", "rk4"])
def test_fast_path_gradient_equals_generic(name):
    """Reverse mode through the fast path (implicit function theorem at every root, with
    the closed-form Jacobian; hand-written tangents of the explicit steps; per-step
    rematerialisation) equals reverse mode through `jax.vmap(simulate)` to ≤ 1e-10
    relative, with respect to every body's inertia, Π₀, g₀ and h, for a loss of the saved
    g and Π; `checkpoint=True` changes nothing. The reference is independent of the
    structure-of-arrays steps: the inertia passed as a (diagonal) tensor, which no kernel
    takes (`vmap(simulate)` of principal moments runs the kernels' steps one body at a
    time, so it shares their derivative rules)."""
    rng = np.random.default_rng(3)
    batch, steps, save_every = 6, 12, 4
    bodies, g0, m0, h = random_batch(rng, batch)
    # Ascending moments: the splitting of a tensor works in the frame of `eigh`, which then
    # is the identity, so both runs compose the sub-flows about the same axes.
    inertia = jnp.sort(bodies.inertia, axis=1)
    weights = (
        jnp.asarray(rng.normal(size=(batch, 4, 3, 3))),
        jnp.asarray(rng.normal(size=(batch, 4, 3))),
    )
    integrator = FAST[name]

    def loss(params, fast, checkpoint=False, tensor=False):
        # g₀ perturbed through the exponential chart, so its gradient is a tangent vector.
        g = g0 @ lievi.SO3.exp(params["g0_chart"])
        moments = params["inertia"]
        sol = lievi.simulate_batch(
            jax.vmap(lievi.RigidBody)(jax.vmap(jnp.diag)(moments) if tensor else moments),
            integrator,
            g,
            params["m0"],
            h=params["h"],
            n_steps=steps,
            save=lievi.Save(every=save_every),
            tuning=lievi.advanced.Tuning(fast=fast),
            system_axis=0,
            checkpoint=checkpoint,
        )
        return jnp.sum(weights[0] * sol.g) + jnp.sum(weights[1] * sol.m)

    params = {"inertia": inertia, "m0": m0, "h": h, "g0_chart": jnp.zeros((batch, 3))}
    reference = jax.grad(loss)(params, False, tensor=True)
    for fast, checkpoint in ((False, False), (True, False), (True, True)):
        gradient = jax.grad(loss)(params, fast, checkpoint)
        for key in params:
            scale = np.max(np.abs(reference[key]))
            assert scale > 0, key
            np.testing.assert_allclose(
                gradient[key], reference[key], rtol=0, atol=1e-10 * scale, err_msg=key
            )


@pytest.mark.parametrize(
    "rows, method",
    [
        pytest.param(3, "splitting", marks=pytest.mark.extended),  # 10 s
        (3, "rk4"),
        (1, "splitting"),
        (1, "rk4"),
    ],
)
def test_explicit_step_derivative_rules(method, rows):
    """The hand-written tangents of the explicit fast steps (`_explicit_adjoints`) equal
    plain autodiff of the same arithmetic, in forward mode (`jvp`) and reverse mode
    (`vjp`), to ≤ 1e-13·max(1, |reference|) (float64, 7 random bodies; all of `g` or one
    row, as the reduced heavy-top state; a per-body or a shared parameter)."""
    rng = np.random.default_rng(11)
    batch = 7

    def arrays(n, low=-1.0, high=1.0):
        return tuple(jnp.asarray(rng.uniform(low, high, batch)) for _ in range(n))

    g, Pi = arrays(3 * rows), arrays(3, -2.0, 2.0)
    if method == "splitting":
        rule, plain = _explicit_adjoints.splitting_flow, _explicit_primal.splitting_primal
        # h/I: per body up to angles of several turns (every quadrant of `sincos`).
        per_body, shared = arrays(3, 0.05, 2.0), tuple(jnp.asarray(x) for x in (0.3, 0.2, 0.1))
    else:
        rule, plain = _explicit_adjoints.rk4_flow, _explicit_primal.rk4_primal
        per_body, shared = arrays(3, 0.05, 0.5), tuple(jnp.asarray(x) for x in (0.1, 0.2, 0.3))

    def close(a, b):
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-13 * max(np.max(np.abs(y)), 1.0))

    for parameters in (per_body, shared):
        primals = (g, Pi, parameters)
        tangents = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=jnp.shape(x))), primals)
        out, tangent = jax.jvp(rule, primals, tangents)
        out_plain, tangent_plain = jax.jvp(lambda *a: plain(*a)[:2], primals, tangents)
        close(out, out_plain)
        close(tangent, tangent_plain)
        cotangent = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape)), out)
        close(
            jax.vjp(rule, *primals)[1](cotangent),
            jax.vjp(lambda *a: plain(*a)[:2], *primals)[1](cotangent),
        )


@pytest.mark.extended  # 12 s
def test_fast_path_gradient_finite_when_a_body_fails():
    """A body whose step fails (a far too large h) is reported and masked; the gradient of
    a loss of the other bodies is finite and equals the generic path's."""
    rng = np.random.default_rng(1)
    bodies, g0, m0, _ = random_batch(rng, 4)
    h = jnp.full(4, 0.1).at[2].set(40.0)
    ok = np.arange(4) != 2

    def loss(inertia, fast):
        sol = lievi.simulate_batch(
            jax.vmap(lievi.RigidBody)(inertia),
            lievi.DEP(max_steps=6),
            g0,
            m0,
            h=h,
            n_steps=6,
            system_axis=0,
            save=lievi.Save(every=6),
            tuning=lievi.advanced.Tuning(fast=fast),
            throw=False,
        )
        # Not |m|²: the Casimir is conserved, so its gradient is round-off noise.
        weights = jnp.array([1.0, -2.0, 3.0])
        return jnp.sum(jnp.where(ok[:, None, None], sol.m, 0.0) * weights), sol.result

    (fast, result) = jax.grad(loss, has_aux=True)(bodies.inertia, True)
    assert result[2] != lievi.RESULTS.successful
    assert np.all(np.isfinite(np.asarray(fast)))
    generic, _ = jax.grad(loss, has_aux=True)(bodies.inertia, False)
    np.testing.assert_allclose(fast[ok], generic[ok], rtol=0, atol=1e-10 * np.abs(generic).max())


@pytest.mark.parametrize(
    "name",
    # All under -m slow: the kernel parity test covers the heavy top's kick kernel against
    # the reference path in the default suite (values and gradients, one body and a batch).
    [pytest.param(n, marks=pytest.mark.slow) for n in ("dep-exp", "splitting", "moser-veselov")],
)
def test_heavy_top_fast_path(name):
    """Rigid bodies in uniform gravity (heavy tops, a batch of masses and centres of mass):
    the fast path (half kick with the closed-form torque `mγ Γ × ρ`, free kernel, half
    kick) equals the generic kick–free–kick step to round-off, values and gradients."""
    rng = np.random.default_rng(4)
    batch = 5
    bodies, g0, m0, _ = random_batch(rng, batch)
    mass = jnp.asarray(rng.uniform(0.5, 1.5, batch))
    com = jnp.asarray(0.3 * rng.normal(size=(batch, 3)))

    def tops(inertia, mass, com):
        return jax.vmap(lambda i, m, c: lievi.RigidBody(i, lievi.UniformGravity(m, c, 1.0)))(
            inertia, mass, com
        )

    integrator = FAST[name]
    assert lievi.advanced.has_fast_path(tops(bodies.inertia, mass, com), integrator, system_axis=0)
    kwargs = dict(h=0.05, n_steps=12, save=lievi.Save(every=4), system_axis=0)

    def run(params, fast):
        return lievi.simulate_batch(
            tops(*params), integrator, g0, m0, tuning=lievi.advanced.Tuning(fast=fast), **kwargs
        )

    params = (bodies.inertia, mass, com)
    fast, generic = run(params, True), run(params, False)
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_allclose(fast.m, generic.m, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.g, generic.g, rtol=0, atol=ROUNDOFF)

    def loss(params, fast):
        sol = run(params, fast)
        return jnp.sum(sol.m**2) + jnp.sum(sol.g[:, -1, 2])

    grad_fast, grad_generic = jax.grad(loss)(params, True), jax.grad(loss)(params, False)
    for a, b in zip(grad_fast, grad_generic):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * np.abs(b).max())

    # The reduced run (g not saved: the fast path carries (Π, Γ)), the same loss with
    # Γ_final = g_finalᵀe₃ read from `Solution.advected`: the same gradient as the g path.
    def reduced_loss(params):
        reduced = {**kwargs, "save": lievi.Save(g=False, stats=False, advected=True, every=4)}
        sol = lievi.simulate_batch(tops(*params), integrator, g0, m0, **reduced)
        assert sol.g is None
        return jnp.sum(sol.m**2) + jnp.sum(sol.advected[:, -1])

    grad_reduced = jax.grad(reduced_loss)(params)
    for a, b in zip(grad_reduced, grad_generic):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * np.abs(b).max())


def heavy_tops(rng, batch):
    """A batch of asymmetric heavy tops with off-axis centres of mass."""
    bodies, g0, m0, _ = random_batch(rng, batch)
    mass = jnp.asarray(rng.uniform(0.5, 1.5, batch))
    com = jnp.asarray(0.3 * rng.normal(size=(batch, 3)))
    tops = jax.vmap(lambda i, m, c: lievi.RigidBody(i, lievi.UniformGravity(m, c, 1.0)))(
        bodies.inertia, mass, com
    )
    return tops, g0, m0


@pytest.mark.parametrize(
    "name",
    [pytest.param("dep-exp", marks=pytest.mark.extended)]  # 18 s
    + [
        pytest.param(n, marks=pytest.mark.slow)
        for n in ("dep-cayley", "moser-veselov", "splitting")
    ],
)
def test_reduced_heavy_top_equals_reconstructed(name):
    """The reduced fast path (paper §7: `(Π, Γ)` with `Γ_{k+1} = F_kᵀΓ_k`, no `g`) gives
    the reconstructed run's `(Π_k, g_kᵀe₃)` to round-off, with the same per-body result
    codes and NaN masking; bodies that fail (a NaN centre of mass: invalid input; a spin
    too fast for the step: step too large) fail alike and do not disturb the others."""
    from lievi._steppers import plan_for

    rng = np.random.default_rng(11)
    batch = 6
    tops, g0, m0 = heavy_tops(rng, batch)
    tops = eqx_set(tops, lambda t: t.potential.center_of_mass, 1, jnp.nan)
    m0 = m0.at[2].set(jnp.array([40.0, -30.0, 20.0]))
    integrator = FAST[name]
    kernel = plan_for(tops, integrator, 0, carry_g=False).kernel
    assert len(kernel.carried(g0)) == 3  # Γ alone, not the 9 entries of g
    kwargs = dict(h=0.05, n_steps=60, system_axis=0, throw=False)
    save = lievi.Save(g=True, m=True, stats=False, advected=True, every=6)
    full = lievi.simulate_batch(tops, integrator, g0, m0, save=save, **kwargs)
    without_g = lievi.Save(g=False, m=True, stats=False, advected=True, every=6)
    reduced = lievi.simulate_batch(tops, integrator, g0, m0, save=without_g, **kwargs)
    assert reduced.g is None and reduced.advected.shape == (batch, 11, 3)
    np.testing.assert_array_equal(reduced.result, full.result)
    np.testing.assert_array_equal(reduced.stats["failed_step"], full.stats["failed_step"])
    assert full.result[1] == lievi.RESULTS.invalid_input
    assert full.result[2] == lievi.RESULTS.step_too_large
    ok = np.asarray(full.result == lievi.RESULTS.successful)
    assert ok.sum() == batch - 2
    # Γ_k = g_kᵀe₃ is the last row of g_k; NaN where the body has failed, in both runs.
    vertical = full.g[..., 2, :]
    np.testing.assert_allclose(full.advected, vertical, rtol=0, atol=0)
    np.testing.assert_array_equal(np.isnan(reduced.advected), np.isnan(vertical))
    assert np.all(np.isnan(reduced.advected[~ok, 1:]))
    np.testing.assert_allclose(reduced.advected[ok], vertical[ok], rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(reduced.m[ok], full.m[ok], rtol=0, atol=ROUNDOFF)
    # The reduced state keeps the Casimirs |Γ|² = 1 and Π·Γ (paper §7).
    gamma, m = reduced.advected[ok], reduced.m[ok]
    np.testing.assert_allclose(np.sum(gamma**2, axis=-1), 1.0, rtol=0, atol=ROUNDOFF)
    pg = np.sum(gamma * m, axis=-1)
    np.testing.assert_allclose(
        pg, np.broadcast_to(pg[:, :1], pg.shape), rtol=0, atol=ROUNDOFF * np.abs(pg).max()
    )


def eqx_set(tree, where, index, value):
    import equinox as eqx

    return eqx.tree_at(where, tree, where(tree).at[index].set(value))


def test_saving_the_advected_parameter_needs_one():
    """`save=lievi.Save(advected=True)` for a system whose potential has no advected
    parameter (a free body, or a plain `V(g)`) is an error naming `save.advected`."""
    _, g0, m0, h = random_batch(np.random.default_rng(2), 3)
    inertia = jnp.array([1.0, 2.0, 3.0])
    for system in (lievi.RigidBody(inertia), lievi.RigidBody(inertia, potential=lambda g: g[2, 2])):
        with pytest.raises(
            ValueError, match="`save.advected` but the system's potential has no advected parameter"
        ):
            lievi.simulate_batch(
                system,
                FAST["dep-exp"],
                g0,
                m0,
                h=h,
                n_steps=2,
                save=lievi.Save(g=False, stats=False, advected=True, every=2),
            )
    with pytest.raises(ValueError, match="`save` may only contain"):
        lievi.simulate_batch(system, FAST["dep-exp"], g0, m0, h=h, n_steps=2, save=("gamma",))
