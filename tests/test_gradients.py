"""Derivatives of whole trajectories: `grad`, `jacfwd`, `jacrev`, `vmap` through
`simulate` with respect to the inertia, Π₀, g₀ (through the exponential chart) and h.

The Newton solve of every DEP (both charts) and Moser–Veselov step is differentiated by the implicit function theorem at
the converged root (`jax.lax.custom_root` in `_newton.py`), so:

- gradients agree with 4th-order central finite differences (relative 1e-6, float64);
- forward and reverse mode agree to 1e-10;
- the gradient does not depend on how many Newton iterations were taken once converged;
- gradients are finite where the step is the identity (Π₀ = 0, so ξ = 0 at every step),
  in float32 and float64, and when a step of the run fails (the failure is reported and
  masked, never NaN);
- `checkpoint=True` changes memory, not numbers.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import hlw_problem
from lievi import SO3
from lievi._newton import newton_solve

N_STEPS = 1000  # the acceptance test: 1000 steps of the HLW body
H = 0.05
SAVE_EVERY = 10
FD_RTOL = 1e-6  # finite differences vs autodiff, relative to the largest component
MODE_RTOL = 1e-10  # jacfwd vs jacrev
ITERATION_RTOL = 1e-10  # gradients at different Newton iteration counts


def _weights(shape, seed):
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape))


W_G = _weights((N_STEPS // SAVE_EVERY + 1, 3, 3), 0)
W_M = _weights((N_STEPS // SAVE_EVERY + 1, 3), 1)


def _params(dtype=jnp.float64):
    body, _, m0 = hlw_problem()
    return {
        "inertia": body.inertia.astype(dtype),
        "m0": m0.astype(dtype),
        "g0_chart": jnp.array([0.1, -0.2, 0.3], dtype),  # g₀ = exp(δ)
        "h": jnp.asarray(H, dtype),
    }


def _trajectory(params, integrator, n_steps=N_STEPS, checkpoint=False):
    sol = lievi.simulate(
        lievi.RigidBody(params["inertia"]),
        integrator,
        SO3.exp(params["g0_chart"]),
        params["m0"],
        h=params["h"],
        n_steps=n_steps,
        save=lievi.Save(every=SAVE_EVERY),
        throw=False,
        checkpoint=checkpoint,
    )
    return sol


def _loss(params, integrator, checkpoint=False, n_steps=N_STEPS):
    """A generic trajectory loss: fixed random weights on every saved `g_k` and `Π_k`."""
    sol = _trajectory(params, integrator, n_steps=n_steps, checkpoint=checkpoint)
    saves = n_steps // SAVE_EVERY + 1
    w_g, w_m = (
        W_G[:saves].astype(sol.g.dtype),
        W_M[:saves].astype(sol.m.dtype),
    )  # float32 stays float32
    return jnp.sum(w_g * sol.g) + jnp.sum(w_m * sol.m)


INTEGRATORS = {
    "exp": lievi.DEP(chart="exp"),
    "cayley": lievi.DEP(chart="cayley"),
    "moser-veselov": lievi.MoserVeselov(),
}


# The Cayley chart shares all code paths but the chart; its copies are `slow` (compile time).
# So are Moser–Veselov's, but for the finite-difference check below, which runs by default.
COMPILED = [
    "exp",
    pytest.param("cayley", marks=pytest.mark.slow),
    pytest.param("moser-veselov", marks=pytest.mark.slow),
]
# The same with the exp chart's case extended, for a heavy check's indirect parametrization.
COMPILED_EXP_EXTENDED = [pytest.param("exp", marks=pytest.mark.extended), *COMPILED[1:]]


@pytest.fixture(scope="module", params=COMPILED)
def compiled(request):
    dep = INTEGRATORS[request.param]
    loss = jax.jit(lambda p: _loss(p, dep))
    grad = jax.jit(jax.grad(lambda p: _loss(p, dep)))
    return dep, loss, grad


def _flat(tree):
    return np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])


def _finite_difference(loss, params):
    """4th-order central differences, one coordinate at a time."""
    leaves, treedef = jax.tree.flatten(params)
    out = []
    for i, leaf in enumerate(leaves):
        flat = np.ravel(np.asarray(leaf))
        for j in range(flat.size):
            # relative step: derivatives in h grow like N per order, so its step is 1e-4·h
            eps = 1e-4 * max(1e-2, abs(flat[j]))

            def at(shift, i=i, j=j, flat=flat, leaf=leaf):
                x = flat.copy()
                x[j] += shift
                new = list(leaves)
                new[i] = jnp.asarray(x.reshape(np.shape(leaf)), leaf.dtype)
                return float(loss(jax.tree.unflatten(treedef, new)))

            out.append((8 * (at(eps) - at(-eps)) - (at(2 * eps) - at(-2 * eps))) / (12 * eps))
    return np.asarray(out)


def test_gradient_matches_finite_differences(compiled):
    _, loss, grad = compiled
    params = _params()
    ad = _flat(grad(params))
    fd = _finite_difference(loss, params)
    assert np.all(np.isfinite(ad))
    np.testing.assert_allclose(ad, fd, rtol=FD_RTOL, atol=FD_RTOL * np.max(np.abs(ad)))


@pytest.mark.extended  # 13 s
def test_moser_veselov_gradient_matches_finite_differences():
    """Implicit differentiation through Moser–Veselov's own Newton solve (default suite)."""
    mv = INTEGRATORS["moser-veselov"]
    params = _params()
    ad = _flat(jax.jit(jax.grad(lambda p: _loss(p, mv)))(params))
    fd = _finite_difference(jax.jit(lambda p: _loss(p, mv)), params)
    assert np.all(np.isfinite(ad))
    np.testing.assert_allclose(ad, fd, rtol=FD_RTOL, atol=FD_RTOL * np.max(np.abs(ad)))


def _final_state(params, integrator, n_steps=200):
    sol = _trajectory(params, integrator, n_steps=n_steps)
    return jnp.concatenate([sol.g[-1].ravel(), sol.m[-1]])


@pytest.mark.parametrize("compiled", COMPILED_EXP_EXTENDED, indirect=True)  # exp: 11 s
def test_jacfwd_equals_jacrev(compiled):
    dep, _, _ = compiled
    params = _params()
    fwd = jax.jit(jax.jacfwd(lambda p: _final_state(p, dep)))(params)
    rev = jax.jit(jax.jacrev(lambda p: _final_state(p, dep)))(params)
    for name in params:
        a, b = np.asarray(fwd[name]), np.asarray(rev[name])
        assert np.all(np.isfinite(a)), name
        np.testing.assert_allclose(
            a, b, rtol=MODE_RTOL, atol=MODE_RTOL * np.max(np.abs(a)), err_msg=name
        )


@pytest.mark.parametrize("compiled", COMPILED_EXP_EXTENDED, indirect=True)  # exp: 14 s
def test_gradient_independent_of_newton_iterations(compiled):
    """Loose vs tight (converged) tolerances: different iteration counts, same gradient."""
    dep, _, grad = compiled
    params = _params()
    # DEP at h = 0.1 reaches a residual ~2e-13 in 2 iterations; the default tolerance (64
    # ulps ≈ 1.4e-14) takes a third one in most steps. Moser–Veselov's quadratic equation
    # converges faster from its guess: at h = 0.2, 2 iterations reach 1e-12 (not 1e-13) and
    # the default takes 3 in every step. Over 1000 such steps (T = 200) the two trajectories
    # drift apart by ~3e-9, through the roots, not the derivatives; 200 steps keep that
    # below the tolerance.
    mv = isinstance(dep, lievi.MoserVeselov)
    h, tol, n_steps = (0.2, 1e-12, 200) if mv else (0.1, 1e-10, N_STEPS)
    params["h"] = jnp.asarray(h)
    # The kernel takes a fixed number of iterations before its first check (3: a body
    # batched or alone); `max_steps=2` caps it, so the loose solve stops after 2.
    loose = dataclasses.replace(dep, rtol=tol, atol=tol, max_steps=2)
    iterations = {
        name: int(_trajectory(params, integrator, n_steps=n_steps).stats["total_newton_iterations"])
        for name, integrator in (("loose", loose), ("default", dep))
    }
    assert iterations["default"] > iterations["loose"] + n_steps // 2, iterations
    tight = _flat(
        jax.jit(jax.grad(lambda p: _loss(p, dep, n_steps=n_steps)))(params) if mv else grad(params)
    )
    loose = _flat(jax.jit(jax.grad(lambda p: _loss(p, loose, n_steps=n_steps)))(params))
    np.testing.assert_allclose(
        loose, tight, rtol=ITERATION_RTOL, atol=ITERATION_RTOL * np.max(np.abs(tight))
    )


def _zero_momentum(dtype):
    params = _params(dtype)
    params["m0"] = jnp.zeros(3, dtype)
    params["g0_chart"] = jnp.zeros(3, dtype)
    return params


def _check_zero_momentum_gradient(grads, dtype):
    for name, value in grads.items():
        assert value.dtype == dtype
        assert np.all(np.isfinite(np.asarray(value))), (name, value)
    # Nothing moves (g_k = I, Π_k = 0), so the inertia has no effect; Π₀ and g₀ have.
    np.testing.assert_array_equal(np.asarray(grads["inertia"]), 0)
    assert np.max(np.abs(np.asarray(grads["m0"]))) > 0
    assert np.max(np.abs(np.asarray(grads["g0_chart"]))) > 0


def test_gradient_finite_at_zero_momentum(compiled):
    """Π₀ = 0 makes every increment ξ_k = 0 and g₀ = exp(0) = I: all at the Taylor branches."""
    _, _, grad = compiled
    _check_zero_momentum_gradient(grad(_zero_momentum(jnp.float64)), jnp.float64)


@pytest.mark.parametrize(
    "chart",
    [
        pytest.param("exp", marks=pytest.mark.extended),  # 11 s
        pytest.param("cayley", marks=pytest.mark.slow),
        pytest.param("moser-veselov", marks=pytest.mark.slow),
    ],
)
def test_gradient_finite_at_zero_momentum_float32(chart):
    dep = INTEGRATORS[chart]
    f32 = jnp.float32
    grads = jax.jit(jax.grad(lambda p: _loss(p, dep)))(_zero_momentum(f32))
    _check_zero_momentum_gradient(grads, f32)


@pytest.mark.slow  # the default suite runs vmap of grad through simulate in test_identification
def test_gradient_under_vmap(compiled):
    """`vmap` of `grad` over a batch of bodies equals the per-body gradients."""
    dep, _, grad = compiled
    params = _params()
    scales = jnp.array([1.0, 1.2, 0.8])
    batch = jax.tree.map(lambda x: jnp.stack([x * s if x.ndim else x for s in scales]), params)
    batched = jax.jit(jax.vmap(jax.grad(lambda p: _loss(p, dep))))(batch)
    for i in range(len(scales)):
        single = grad(jax.tree.map(lambda x: x[i], batch))
        for name in params:
            # Under vmap the Newton loop runs until every body's solve has converged, so a
            # body may take an extra (converged) iteration: agreement to ITERATION_RTOL.
            np.testing.assert_allclose(
                batched[name][i],
                single[name],
                rtol=ITERATION_RTOL,
                atol=ITERATION_RTOL * np.max(np.abs(single[name])),
            )


@pytest.mark.parametrize(
    "compiled, checkpoint",
    # True → 40-step segments spanning 4 saves; 5 → two segments inside each 10-step save.
    [
        pytest.param("exp", True, marks=pytest.mark.extended, id="exp-True"),  # 13 s
        pytest.param("exp", 5, marks=pytest.mark.slow, id="exp-5"),
    ]
    + [
        pytest.param(chart, checkpoint, marks=pytest.mark.slow, id=f"{chart}-{checkpoint}")
        for chart in ("cayley", "moser-veselov")
        for checkpoint in (True, 5)
    ],
    indirect=["compiled"],
)
def test_checkpointing_changes_nothing(compiled, checkpoint):
    dep, loss, grad = compiled
    params = _params()
    value, ckpt = jax.jit(jax.value_and_grad(lambda p: _loss(p, dep, checkpoint=checkpoint)))(
        params
    )
    np.testing.assert_allclose(float(value), float(loss(params)), rtol=1e-14)
    np.testing.assert_allclose(_flat(ckpt), _flat(grad(params)), rtol=1e-12, atol=1e-12)


def test_checkpoint_argument_checked():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="checkpoint"):
        lievi.simulate(
            body, lievi.DEP(), g0, m0, h=0.1, n_steps=100, save=lievi.Save(every=10), checkpoint=30
        )
    with pytest.raises(ValueError, match="checkpoint"):
        lievi.simulate(
            body, lievi.DEP(), g0, m0, h=0.1, n_steps=100, save=lievi.Save(every=10), checkpoint=3
        )


@pytest.mark.extended  # 12 s
def test_gradient_finite_when_a_step_fails():
    """A step that fails (here: rotation ≥ π in one step) is reported and masked; the
    gradient of a loss over the valid part of the trajectory stays finite."""
    body, g0, m0 = hlw_problem()

    def loss(inertia, h):
        sol = lievi.simulate(
            lievi.RigidBody(inertia), lievi.DEP(), g0, m0, h=h, n_steps=20, throw=False
        )
        valid = jnp.all(jnp.isfinite(sol.m), axis=-1)
        # double where: the masked entries never enter an arithmetic expression
        g = jnp.where(valid[:, None, None], sol.g, 0.0)
        return jnp.sum(W_G[:21] * g), (sol.result, sol.stats["failed_step"])

    # A momentum off the principal plane: |Ω| grows along the orbit, so the step first
    # passes the step bound (h|Ω| ≤ π, docs/guarantees.md) a few steps in.
    m0 = jnp.array([np.cos(1.1), 0.3, np.sin(1.1)])
    grad = jax.jit(jax.grad(loss, has_aux=True))
    value, (result, failed_step) = grad(body.inertia, 2.26)  # fails at step 5
    assert int(result) == lievi.RESULTS.step_too_large and int(failed_step) > 0
    assert np.all(np.isfinite(np.asarray(value)))
    assert np.max(np.abs(np.asarray(value))) > 0  # the steps before the failure count


def test_newton_divergence_gives_finite_gradient():
    """A Newton solve that runs into NaN returns its finite starting point, so the implicit
    derivative of a masked output is 0 rather than NaN (`_newton.py`)."""

    def solve(p):
        # √x = p has no root for p < 0; from x = 1 the first Newton step lands at x < 0.
        x, info = newton_solve(lambda x: jnp.sqrt(x) - p, jnp.ones(1), 1e-12, 10)
        return jnp.where(info.converged, x[0], 0.0), info.converged

    dx, converged = jax.grad(solve, has_aux=True)(-1.0)
    assert not bool(converged) and float(dx) == 0.0
    dx, converged = jax.grad(solve, has_aux=True)(2.0)
    assert bool(converged) and float(dx) == pytest.approx(4.0, rel=1e-12)  # x = p², dx/dp = 2p
