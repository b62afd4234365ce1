"""`simulate_batch` on SE(3): the structure-of-arrays DEP step (`lievi/_kernels/_se3.py`)
equals the generic path (`jax.vmap(simulate)`) to round-off, in values, result codes and
gradients; its reduced Newton iteration's Jacobian equals `jax.jacfwd`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, ROUNDOFF_F32
from lievi._kernels import _se3, _se3_reduced, _se3_residual
from lievi._kernels._base import compacted_tail, reference_path

SE3 = lievi.SE3
CHARTS = ("exp", "cayley")
BATCH, STEPS, SAVE_EVERY = 8, 20, 5


def random_tensors(rng, batch, kind):
    """`kind`: "kirchhoff" (a full SPD 6×6 tensor) or "vacuum" (`diag(J, m1)`)."""
    if kind == "kirchhoff":
        B = rng.normal(size=(batch, 6, 6))
        tensors = B @ np.swapaxes(B, -1, -2) / 6 + np.diag([1.0, 1.5, 2.0, 3.0, 4.0, 5.0])
        return jnp.asarray(tensors)
    inertia = rng.uniform(0.5, 2.0, size=(batch, 3))
    mass = rng.uniform(1.0, 3.0, size=batch)
    return jax.vmap(lambda J, m: lievi.RigidBodySE3(J, m).tensor)(
        jnp.asarray(inertia), jnp.asarray(mass)
    )


def random_batch(rng, batch, kind="kirchhoff"):
    tensors = random_tensors(rng, batch, kind)
    bodies = jax.vmap(lambda M: lievi.RigidBodySE3(tensor=M))(tensors)
    g0 = jax.vmap(SE3.exp)(jnp.asarray(rng.normal(size=(batch, 6))))
    m0 = jnp.asarray(rng.normal(size=(batch, 6)))
    h = jnp.asarray(rng.uniform(0.02, 0.2, size=batch))
    return bodies, g0, m0, h


# Under -m slow: the kernel parity test covers the kernel against the reference path in the
# default suite (both charts, one body and a batch); these add per-body step sizes, vacuum
# tensors and 20 steps.
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["kirchhoff", "vacuum"])
@pytest.mark.parametrize("chart", CHARTS)
def test_fast_equals_generic(chart, kind):
    """Poses with translations, one system and one step per body: the same `g`, `m`,
    result codes as the generic path, residuals within the Newton tolerance."""
    bodies, g0, m0, h = random_batch(np.random.default_rng(5), BATCH, kind)
    dep = lievi.DEP(chart=chart)
    assert lievi.advanced.has_fast_path(bodies, dep, system_axis=0)
    kwargs = dict(h=h, n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY), system_axis=0)
    fast = lievi.simulate_batch(bodies, dep, g0, m0, **kwargs)
    generic = lievi.simulate_batch(
        bodies, dep, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    assert fast.g.shape == generic.g.shape == (BATCH, STEPS // SAVE_EVERY + 1, 4, 4)
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_array_equal(generic.result, 0)
    np.testing.assert_array_equal(fast.stats["failed_step"], -1)
    np.testing.assert_allclose(fast.ts, generic.ts, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.g, generic.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.m, generic.m, rtol=0, atol=ROUNDOFF)
    bound = 64 * np.finfo(np.float64).eps * np.abs(fast.m).max(axis=(1, 2))
    assert np.all(fast.stats["residual"] <= bound[:, None])
    # The fast path's last row stays exactly (0, 0, 0, 1).
    np.testing.assert_array_equal(fast.g[:, :, 3], np.broadcast_to([0, 0, 0, 1.0], (BATCH, 5, 4)))


@pytest.mark.extended  # 51 s
def test_float32():
    """float32 in, float32 out: the fast path matches the generic float32 run and the
    float64 one to float32 round-off."""
    bodies, g0, m0, _ = random_batch(np.random.default_rng(6), BATCH)
    body = lievi.RigidBodySE3(tensor=bodies.tensor[0].astype(jnp.float32))
    g32, m32 = g0.astype(jnp.float32), m0.astype(jnp.float32)
    dep = lievi.DEP(chart="cayley")
    kwargs = dict(n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY))
    fast = lievi.simulate_batch(body, dep, g32, m32, h=jnp.float32(0.05), **kwargs)
    generic = lievi.simulate_batch(
        body, dep, g32, m32, h=jnp.float32(0.05), tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    body64 = lievi.RigidBodySE3(tensor=body.tensor.astype(jnp.float64))
    exact = lievi.simulate_batch(
        body64, dep, g32.astype(float), m32.astype(float), h=0.05, **kwargs
    )
    assert fast.m.dtype == jnp.float32 and fast.g.dtype == jnp.float32
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_allclose(fast.m, generic.m, rtol=0, atol=ROUNDOFF_F32)
    np.testing.assert_allclose(fast.m, exact.m, rtol=0, atol=ROUNDOFF_F32)
    np.testing.assert_allclose(fast.g, exact.g, rtol=0, atol=ROUNDOFF_F32)


@pytest.mark.slow  # the tail runs in the default suite: stragglers and the Newton sweep
def test_shared_system_one_fixed_iteration_then_tail():
    """One system for all bodies, one fixed iteration (the chord step): the `while_loop`
    tail finishes every body, with the same iterates as the generic path."""
    rng = np.random.default_rng(2)
    bodies, g0, m0, _ = random_batch(rng, BATCH)
    body = lievi.RigidBodySE3(tensor=bodies.tensor[0])
    dep = lievi.DEP(chart="exp")
    kwargs = dict(h=0.1, n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY))
    one = lievi.simulate_batch(
        body, dep, g0, m0, tuning=lievi.advanced.Tuning(fixed_iterations=1), **kwargs
    )
    generic = lievi.simulate_batch(
        body, dep, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    np.testing.assert_allclose(one.g, generic.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(one.m, generic.m, rtol=0, atol=ROUNDOFF)
    assert np.all(one.stats["newton_iterations"] >= 2)  # the tail ran


@pytest.mark.parametrize(
    "chart",
    [
        pytest.param("exp", marks=pytest.mark.extended),  # 33 s
        pytest.param("cayley", marks=pytest.mark.slow),
    ],
)
def test_stragglers_take_the_gathered_tail(chart):
    """A few bodies with large steps among many small ones: only they continue after the
    fixed iterations (gathered into a small batch, `compacted_tail`), and every body ends
    on the generic path's iterates."""
    rng = np.random.default_rng(9)
    batch = 64
    bodies, g0, m0, _ = random_batch(rng, batch)
    body = lievi.RigidBodySE3(tensor=bodies.tensor[0])
    m0 = m0.at[:3].multiply(12.0)  # 3 stragglers: |ξ| ≈ 0.75, beyond what 3 iterations reach
    dep = lievi.DEP(chart=chart)
    kwargs = dict(h=0.05, n_steps=STEPS, save=lievi.Save(every=SAVE_EVERY))
    fast = lievi.simulate_batch(body, dep, g0, m0, **kwargs)
    generic = lievi.simulate_batch(
        body, dep, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_allclose(fast.g, generic.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.m, generic.m, rtol=0, atol=ROUNDOFF)
    fixed = _se3.DEFAULT_FIXED_ITERATIONS[chart]
    most = fast.stats["newton_iterations"].max(axis=1)
    assert np.all(most[:3] > fixed) and np.all(most[3:] == fixed)


@pytest.mark.parametrize("alive", ["all", "some"])
@pytest.mark.parametrize("n_need", [0, 3, 20])
def test_compacted_tail(n_need, alive):
    """`compacted_tail` equals its loop run on the whole batch, whichever branch it takes
    (none, gathered: at most B/8 bodies, whole batch), and leaves failed bodies alone."""
    batch = 64
    rng = np.random.default_rng(n_need)
    x = jnp.zeros(batch, jnp.int32)
    target = (
        jnp.zeros(batch, jnp.int32)
        .at[rng.permutation(batch)[:n_need]]
        .set(jnp.asarray(rng.integers(1, 5, size=n_need), jnp.int32))
    )
    mask = True if alive == "all" else jnp.asarray(rng.uniform(size=batch) > 0.3)

    def run(state, args):
        target, alive = args

        def on(state):
            return alive & (state[0] < target)

        def body(state):
            step = on(state).astype(jnp.int32)
            return state[0] + step, state[1] + 10 * step

        return jax.lax.while_loop(lambda s: jnp.any(on(s)), body, state)

    state, args = (x, x + 7), (target, mask)
    need = mask & (x < target)
    got = jax.jit(lambda s, a: compacted_tail(need, run, s, a))(state, args)
    expected = run(state, args)
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a, b)
    assert int(jnp.sum(got[0] != x)) == int(jnp.sum(need))


def _stacked_rho(chart, m, C):
    """The reduced residual `ρ` as a function of a stacked `ω` (for `jax.jacfwd`)."""

    def rho(w):
        return jnp.stack(_se3_reduced.reduced_residual(chart, tuple(w), m, C, False)[0])

    return rho


@pytest.mark.parametrize("chart", CHARTS)
def test_reduced_jacobian(chart):
    """The reduced residual `ρ(ω) = r_ω(ω, v(ω))` with `r_v(ω, v(ω)) = 0` and its
    closed-form Jacobian, against the 6×6 residual and `jax.jacfwd`, at rotation angles
    1e-9 … 2.5."""
    rng = np.random.default_rng(3)
    tensor = random_tensors(rng, 1, "kirchhoff")[0]
    h = 0.1
    kernel = _se3.SE3NewtonKernel(chart, None, None, 20)
    # A tensor shared by the batch: per-run constants are scalars.
    A, _, C = kernel.prepare(kernel.constants(tensor), h)

    @jax.jit
    @jax.vmap
    def errors(w, m):
        m = tuple(m)
        rho = _stacked_rho(chart, m, C)
        r, J, (_, v) = _se3_reduced.reduced_residual(chart, tuple(w), m, C, True)
        full, _ = _se3_residual.residual(chart, tuple(w) + tuple(v), m, A, False)
        J = jnp.stack([jnp.stack(row) for row in J])
        return (
            jnp.max(jnp.abs(jnp.stack(r) - jnp.stack(full[:3]))),
            jnp.max(jnp.abs(jnp.stack(full[3:]))),
            jnp.max(jnp.abs(J - jax.jacfwd(rho)(w))) / jnp.max(jnp.abs(J)),
        )

    angles = jnp.array([1e-9, 1e-3, 0.3, 2.5])
    w = jnp.asarray(rng.normal(size=(4, 3)))
    w = angles[:, None] * w / jnp.linalg.norm(w, axis=-1)[:, None]
    for error in errors(w, jnp.asarray(rng.normal(size=(4, 6)))):
        assert float(jnp.max(error)) <= ROUNDOFF


@pytest.mark.parametrize("chart", CHARTS)
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_chord_jacobian(chart, sign):
    """The chord step's matrix is `∂ρ/∂ω` at `ω = 0` for each body's own momentum
    (`jax.jacfwd` of the reduced residual), for general tensors (`A₁₂ ≠ 0`), momenta of
    every size and either sign of `h` (a composition's negative stages), to round-off."""
    rng = np.random.default_rng(6)
    tensors = random_tensors(rng, 8, "kirchhoff")
    kernel = _se3.SE3NewtonKernel(chart, None, None, 20)
    _, _, C = kernel.prepare(kernel.constants(tensors), sign * 0.1)
    momenta = jnp.asarray(rng.normal(size=(8, 6)) * rng.uniform(0.1, 10.0, size=(8, 1)))

    @jax.jit
    @jax.vmap
    def error(C, m):
        m = tuple(m)
        rho = _stacked_rho(chart, m, C)
        J0 = jnp.stack([jnp.stack(row) for row in _se3._chord_jacobian(chart, m, C)])
        exact = jax.jacfwd(rho)(jnp.zeros(3, m[0].dtype))
        return jnp.max(jnp.abs(J0 - exact)) / jnp.max(jnp.abs(exact))

    C = jax.tree.map(lambda X: jnp.moveaxis(X, -1, 0), C)  # bodies first, for `jax.vmap`
    assert float(jnp.max(error(C, momenta))) <= ROUNDOFF


@pytest.mark.parametrize("chart", CHARTS)
def test_fixed_iterations_suffice_at_coarse_steps(chart):
    """2000 random free bodies (principal moments 0.5–2, masses 0.5–3, `|ω| ≤ 0.3`,
    speeds up to 3) at `h = 0.2`: the fixed iterations alone (`max_steps` equal to them, so
    that a body they leave above the tolerance is reported failed) take every body through
    5 steps. With the momentum-free chord matrix (the Schur complement alone), 7.6 % of
    them (Cayley) and 0.55 % (exp) needed the Newton loop within those steps."""
    rng = np.random.default_rng(0)
    batch = 2000
    inertia, mass = rng.uniform(0.5, 2.0, (batch, 3)), rng.uniform(0.5, 3.0, batch)
    bodies = jax.vmap(lievi.RigidBodySE3)(jnp.asarray(inertia), jnp.asarray(mass))
    w = rng.normal(size=(batch, 3))
    w *= (rng.uniform(0.0, 0.3, batch) / np.linalg.norm(w, axis=1))[:, None]
    v = rng.normal(size=(batch, 3)) * rng.uniform(0.0, 3.0, (batch, 1))
    m0 = jnp.asarray(np.concatenate([inertia * w, mass[:, None] * v], axis=1))
    fixed = _se3.DEFAULT_FIXED_ITERATIONS[chart]
    sol = lievi.simulate_batch(
        bodies,
        lievi.DEP(chart=chart, max_steps=fixed),
        jnp.broadcast_to(jnp.eye(4), (batch, 4, 4)),
        m0,
        h=0.2,
        n_steps=5,
        system_axis=0,
        throw=False,
        save=lievi.Save(every=5),
    )
    np.testing.assert_array_equal(sol.result, lievi.RESULTS.successful)


def test_fixed_iterations_suffice_for_a_fast_translating_body():
    """A body whose translation per step is a sizable part of its radius of gyration (the
    lighter body of a binary asteroid, about 0.6 of it): with the chord step's matrix for
    the body's own momentum, the fixed iterations (a chord step, two Newton steps) reach the
    tolerance at every one of 200 steps with either chart, so the Newton loop after them
    never runs. With the momentum-free Schur complement in its place, Cayley's chart needed
    the loop at 24 of these steps."""
    points = jnp.array(
        [
            [[0.12, 0.0, 0.0], [-0.1, 0.08, 0.0], [0.0, -0.06, 0.09]],
            [[0.1, 0.0, 0.02], [-0.08, 0.07, 0.0], [0.0, -0.05, -0.08]],
        ]
    )
    masses = jnp.array([[1.0, 0.6, 0.8], [0.5, 0.4, 0.3]])
    bodies = lievi.gravitating_bodies(1.0, masses, points)
    momentum = 2.4 * 1.2 / 3.6 * jnp.sqrt(2.4)  # a circular mutual orbit 1.5 apart
    g0 = jnp.tile(jnp.eye(4), (2, 1, 1)).at[:, 0, 3].set(jnp.array([-0.5, 1.0]))
    m0 = jnp.array(
        [[0.003, 0.005, 0.01, 0.0, -momentum, 0.0], [0.004, -0.002, 0.001, 0.0, momentum, 0.0]]
    )
    for chart in CHARTS:
        sol = lievi.simulate(bodies, lievi.DEP(chart=chart), g0, m0, h=0.05, n_steps=200)
        assert sol.result == lievi.RESULTS.successful
        fixed = _se3.DEFAULT_FIXED_ITERATIONS[chart]
        np.testing.assert_array_equal(sol.stats["newton_iterations"], fixed)


# The SE(3) kernel's gradients against the generic path run by default in
# tests/test_kernel_parity.py; these longer runs are under -m slow.
@pytest.mark.slow
@pytest.mark.parametrize("chart", ["exp", "cayley"])
def test_gradient_equals_generic(chart):
    """Reverse mode through the fast path (implicit function theorem at each root, with the
    closed-form 6×6 Jacobian) equals reverse mode through the generic path to ≤ 1e-10
    relative, with respect to every body's tensor, m₀, g₀ and h; `checkpoint=True`
    changes nothing."""
    rng = np.random.default_rng(4)
    batch, steps, save_every = 4, 9, 3
    bodies, g0, m0, h = random_batch(rng, batch)
    weights = (
        jnp.asarray(rng.normal(size=(batch, 4, 4, 4))),
        jnp.asarray(rng.normal(size=(batch, 4, 6))),
    )
    dep = lievi.DEP(chart=chart)

    def loss(params, fast, checkpoint=False):
        # g₀ perturbed through the exponential chart, so its gradient is a twist.
        g = g0 @ jax.vmap(SE3.exp)(params["g0_chart"])
        sol = lievi.simulate_batch(
            jax.vmap(lambda M: lievi.RigidBodySE3(tensor=M))(params["tensor"]),
            dep,
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

    params = {"tensor": bodies.tensor, "m0": m0, "h": h, "g0_chart": jnp.zeros((batch, 6))}
    reference = jax.grad(loss)(params, False)
    for checkpoint in (False, True):
        gradient = jax.grad(loss)(params, True, checkpoint)
        for key in params:
            scale = np.max(np.abs(reference[key]))
            assert scale > 0, key
            np.testing.assert_allclose(
                gradient[key], reference[key], rtol=0, atol=1e-10 * scale, err_msg=key
            )


@pytest.mark.extended  # 40 s
def test_failures_are_reported_per_body():
    """A body with a far too large step fails with the generic path's result code at the
    same step, the others carry on unchanged; a Newton budget below what the step needs
    gives `newton_not_converged` for every body, never a silent number; throw=True raises."""
    rng = np.random.default_rng(1)
    bodies, g0, m0, _ = random_batch(rng, 6)
    h = jnp.full(6, 0.1).at[2].set(40.0)
    dep = lievi.DEP(max_steps=6)
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

    one_step = lievi.DEP(max_steps=1)
    kwargs = dict(h=0.1, n_steps=2, system_axis=0, throw=False)
    fast = lievi.simulate_batch(bodies, one_step, g0, m0, **kwargs)
    generic = lievi.simulate_batch(
        bodies, one_step, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    np.testing.assert_array_equal(fast.result, lievi.RESULTS.newton_not_converged)
    np.testing.assert_array_equal(generic.result, lievi.RESULTS.newton_not_converged)
    assert np.all(np.isnan(fast.m[:, -1]))


def test_which_systems_take_the_fast_path():
    """The free body takes it (DEP, both charts); a potential, or a method without an SE(3)
    kernel, keeps the generic path; `g0` is checked with the group's own membership test."""
    body = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
    for chart in CHARTS:
        assert lievi.advanced.has_fast_path(body, lievi.DEP(chart=chart))
    assert not lievi.advanced.has_fast_path(body, lievi.RK4())
    assert not lievi.advanced.has_fast_path(body, lievi.MoserVeselov())
    falling = lievi.RigidBodySE3(
        jnp.array([1.0, 2.0, 3.0]),
        2.0,
        potential=lievi.UniformGravitySE3(2.0, 9.81, jnp.array([0.1, 0.0, 0.05])),
    )
    assert not lievi.advanced.has_fast_path(falling, lievi.DEP())
    g0 = jnp.broadcast_to(jnp.eye(4), (2, 4, 4)).at[1, 3, 0].set(0.5)
    with pytest.raises(ValueError, match=r"`g0\[1\]` is not in the group.*last row"):
        lievi.simulate_batch(
            body, lievi.DEP(), g0, jnp.ones((2, 6)), h=0.1, n_steps=1, save=lievi.Save(every=1)
        )


def sweep(rng, batch, condition, ratios, turn=0.3, h=0.1):
    """`batch` bodies with random kinetic tensors (eigenvalues log-uniform in
    `[1, condition]`, random frame), each given the momentum `M ξ/h` of an increment
    `ξ = (ω, v)` that turns by up to `turn` rad per step and translates by
    `|v| = ratio·|ω|` (per step), the ratio log-uniform in `ratios`."""
    tensors, momenta = [], []
    for _ in range(batch):
        Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
        M = Q @ np.diag(np.exp(rng.uniform(0, np.log(condition), 6))) @ Q.T
        w = rng.normal(size=3)
        w *= rng.uniform(0, turn) / np.linalg.norm(w)
        v = rng.normal(size=3)
        v *= np.exp(rng.uniform(*np.log(ratios))) * np.linalg.norm(w) / np.linalg.norm(v)
        tensors.append(M)
        momenta.append(M @ np.concatenate([w, v]) / h)
    return jnp.asarray(np.array(tensors)), jnp.asarray(np.array(momenta)), h


def assert_kernel_converges_where_newton_does(tensors, m0, h, chart):
    """One step per body through the kernel (`simulate_batch`) and through the generic
    path (`jax.vmap(simulate)` with every kernel off: Newton on the six-component
    residual, `jax.jacfwd`, `linalg.solve`). Wherever the generic Newton converges within
    half its budget (beyond that its path is decided by rounding: the two ways of
    evaluating the same residual then part), the kernel reports success, on the same
    root: the momenta agree to 1e-10 relative. (Two roots of (4.8) differ by O(|m|); two
    evaluations of the same root by the residual tolerance, 64 ulps of `|m|`, amplified by
    the conditioning of the residual's Jacobian, which large translations per step make
    far worse than `M`'s: measured up to 1.1e-12 relative in this sweep.)"""
    batch = tensors.shape[0]
    dep = lievi.DEP(chart=chart)
    g0 = jnp.broadcast_to(jnp.eye(4), (batch, 4, 4))
    bodies = jax.vmap(lambda M: lievi.RigidBodySE3(tensor=M))(tensors)
    fast = lievi.simulate_batch(
        bodies, dep, g0, m0, h=h, n_steps=1, system_axis=0, throw=False, save=lievi.Save(every=1)
    )
    with reference_path():
        generic = jax.jit(
            jax.vmap(
                lambda M, m: lievi.simulate(
                    lievi.RigidBodySE3(tensor=M), dep, jnp.eye(4), m, h=h, n_steps=1, throw=False
                )
            )
        )(tensors, m0)
    converges = (np.asarray(generic.result) == 0) & (
        np.asarray(generic.stats["newton_iterations"])[:, 0] <= dep.max_steps // 2
    )
    assert converges.mean() > 0.8  # the sweep is mostly solvable: the test tests something
    failed = np.nonzero(converges & (np.asarray(fast.result) != 0))[0]
    assert failed.size == 0, f"kernel fails where Newton converges: bodies {failed.tolist()}"
    scale = np.abs(np.asarray(m0)).max(axis=1)
    error = np.abs(np.asarray(fast.m[:, -1] - generic.m[:, -1])).max(axis=1)
    assert np.all(error[converges] <= 1e-10 * scale[converges])


@pytest.mark.extended  # 15–21 s each
@pytest.mark.parametrize("chart", CHARTS)
def test_kernel_converges_where_newton_does(chart):
    """Tensors of condition number up to 1e4 and translation/rotation per step from 1e-3
    to 1e3: the reduced iteration diverges or stalls for many of them, and those bodies
    finish on the full 6×6 Newton from the guess (`_se3._newton_tail`)."""
    tensors, m0, h = sweep(np.random.default_rng(11), 256, 1e4, (1e-3, 1e3))
    assert_kernel_converges_where_newton_does(tensors, m0, h, chart)


@pytest.mark.slow
@pytest.mark.parametrize("chart", CHARTS)
def test_kernel_converges_where_newton_does_wide(chart):
    """2000 bodies of condition number ≤ 100 turning ≤ 0.3 rad and translating ≤ 1 length
    unit per step (the reduced iteration alone failed for 7 % of them on the exp chart),
    and 2000 of condition ≤ 1e4 with translation/rotation ratios 1e-3…1e3."""
    rng = np.random.default_rng(12)
    for condition, ratios in ((100.0, (1e-3, 1 / 0.3)), (1e4, (1e-3, 1e3))):
        tensors, m0, h = sweep(rng, 2000, condition, ratios)
        assert_kernel_converges_where_newton_does(tensors, m0, h, chart)


@pytest.mark.parametrize(
    "chart",
    [
        pytest.param("exp", marks=pytest.mark.extended),  # 39 s
        pytest.param("cayley", marks=pytest.mark.slow),
    ],
)
def test_linear_momentum_sets_the_tolerance(chart):
    """A body whose angular momentum is 10⁻⁵ of its linear momentum (a slow-spinning
    body in orbit): the Newton tolerance is 64 ulps of `‖m‖_∞` over all six components,
    as on the generic path, and so is the convergence test. A norm of the rotational
    components alone asked for a rotational residual below the rounding of its
    translational terms, and the kernel reported a failure where Newton converges."""
    rng = np.random.default_rng(21)
    inertia = jnp.asarray(rng.uniform(1e-4, 1e-3, size=(64, 3)))
    bodies = jax.vmap(lambda J: lievi.RigidBodySE3(J, 2.2))(inertia)
    Pi = rng.normal(size=(64, 3)) * 1e-5
    P = rng.normal(size=(64, 3))
    m0 = jnp.asarray(np.concatenate([Pi, P], axis=1))
    g0 = jnp.broadcast_to(jnp.eye(4), (64, 4, 4))
    dep = lievi.DEP(chart=chart)
    kwargs = dict(h=0.01, n_steps=100, save=lievi.Save(every=100), system_axis=0, throw=False)
    fast = lievi.simulate_batch(bodies, dep, g0, m0, **kwargs)
    generic = lievi.simulate_batch(
        bodies, dep, g0, m0, tuning=lievi.advanced.Tuning(fast=False), **kwargs
    )
    np.testing.assert_array_equal(generic.result, 0)
    np.testing.assert_array_equal(fast.result, 0)
    # Values: the generic path's to ROUNDOFF relative to ‖m‖_∞ (measured 1.3e-13 relative).
    scale = np.abs(np.asarray(m0)).max(axis=1, keepdims=True)
    error = np.abs(np.asarray(fast.m[:, -1] - generic.m[:, -1])).max()
    assert error <= ROUNDOFF * scale.max()
