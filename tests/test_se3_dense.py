"""The one-body SE(3) DEP step on whole arrays (`lievi/_kernels/_se3_dense.py`): the same
iterates as the structure-of-arrays step (`_se3.py`) to round-off, its closed-form
Jacobian equal to `jax.jacfwd` of the generic residual, gradients equal to the generic
path's, float32, the failure codes, a program a fraction of the batch step's, and an
eager run's whole-array state carried across its blocks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, ROUNDOFF_F32
from lievi._kernels import _se3_dense

SE3 = lievi.SE3


def _tensor(seed=3):
    B = np.random.default_rng(seed).normal(size=(6, 6))
    return jnp.asarray(B @ B.T / 6 + np.diag([1.0, 1.5, 2.0, 3.0, 4.0, 5.0]))


def _states(count, seed=4):
    """Poses with translations, momenta turning the body by up to about 2 rad a step."""
    rng = np.random.default_rng(seed)
    g = jax.vmap(SE3.exp)(jnp.asarray(rng.normal(size=(count, 6))))
    m = jnp.asarray(rng.normal(size=(count, 6))) * jnp.linspace(0.01, 3.0, count)[:, None]
    return g, m


def _one_step(kernel, M, g, m, h):
    params = kernel.prepare(kernel.constants(M), h)
    state = kernel.carried(g), kernel.carried_momentum(m)  # the kernel's own layout
    g1, m1, *info = kernel.step(params, *state, jnp.ones(len(m), bool))
    return kernel.elements(jnp.stack(g1)[None])[:, 0], jnp.stack(m1, -1), *info


@pytest.mark.slow  # compiles the batch step (about 10 s); the default suite checks the
# one-body step against the generic path (`tests/test_se3_body.py`) and its Jacobian here
@pytest.mark.parametrize("chart", ["exp", "cayley"])
def test_dense_step_equals_structure_of_arrays_step(chart):
    """Eight bodies, both signs of `h` (a composition's negative stages): the dense step,
    one body at a time (its own Newton loop), and the batch kernel agree to round-off in
    `g`, `m`, the result codes, and converge to the same tolerance."""
    soa = lievi.DEP(chart=chart).kernels()[1]
    dense = soa.one_body()
    assert isinstance(dense, _se3_dense.SE3DenseKernel)
    M = _tensor()
    g, m = _states(8)
    soa_step = jax.jit(lambda g, m, h: _one_step(soa, M, g, m, h))
    dense_step = jax.jit(lambda g, m, h: _one_step(dense, M, g, m, h))
    for h in (0.1, -0.1):
        a = soa_step(g, m, h)
        ones = [dense_step(g[i : i + 1], m[i : i + 1], h) for i in range(len(m))]
        b = [jnp.concatenate(parts) for parts in zip(*ones)]
        np.testing.assert_array_equal(a[2], lievi.RESULTS.successful)
        np.testing.assert_array_equal(b[2], lievi.RESULTS.successful)
        np.testing.assert_allclose(b[0], a[0], rtol=0, atol=ROUNDOFF)
        np.testing.assert_allclose(b[1], a[1], rtol=0, atol=ROUNDOFF * float(jnp.abs(m).max()))
        assert np.all(b[4] <= 64 * np.finfo(np.float64).eps * np.abs(m).max(-1))


@pytest.mark.parametrize("chart", ["exp", "cayley"])
def test_closed_form_jacobian_equals_autodiff(chart):
    """`_residual_and_jacobian` against the generic residual `dφ⁻¹(ξ)ᵀ Aξ − m` (from
    `SE3.dexpinv`/`dcayinv`) and its `jax.jacfwd`, at rotation angles 1e-9 … 2.5."""
    dchart_inverse = SE3.dexpinv if chart == "exp" else SE3.dcayinv
    rng = np.random.default_rng(5)
    A = _tensor() / 0.1
    angles = jnp.array([1e-9, 1e-3, 0.3, 2.5])
    xi = jnp.asarray(rng.normal(size=(4, 6)))
    xi = xi.at[:, :3].set(
        angles[:, None] * xi[:, :3] / jnp.linalg.norm(xi[:, :3], axis=-1)[:, None]
    )
    m = jnp.asarray(rng.normal(size=(4, 6)))
    equation = lievi.DEP(chart=chart).chart

    @jax.jit
    @jax.vmap
    def errors(x, m):
        def generic(y):
            return dchart_inverse(y).T @ (A @ y) - m

        r, J = _se3_dense._residual_and_jacobian(equation, x, m, A)
        return (
            jnp.max(jnp.abs(r - generic(x))) / jnp.max(jnp.abs(A @ x)),
            jnp.max(jnp.abs(J - jax.jacfwd(generic)(x))) / jnp.max(jnp.abs(J)),
        )

    for error in errors(xi, m):
        assert float(jnp.max(error)) <= ROUNDOFF


@pytest.mark.slow  # two reverse passes compiled; the parity registry compares gradients too
def test_gradients_equal_generic_path():
    """The implicit derivative of the dense step's root (`_at_root`) against the generic
    path's (`DEP.solve_increment`, `jax.lax.custom_root`): a loss of one step's `g` and `m`
    differentiated with respect to `m` and the tensor `M`."""
    dep, h = lievi.DEP(), 0.1
    g, m = _states(1, seed=6)
    g, m = g[0], m[0]
    weights = jnp.arange(16.0).reshape(4, 4)

    def loss(g1, m1):
        return jnp.sum(jnp.sin(m1)) + jnp.sum(weights * g1**2)

    def dense(m, M):
        kernel = dep.kernels()[1].one_body()
        g1, m1, *_ = _one_step(kernel, M, g[None], m[None], h)
        return loss(g1[0], m1[0])

    def generic(m, M):
        xi, _ = dep.solve_increment(lievi.RigidBodySE3(tensor=M), m, h)
        F = SE3.exp(xi)
        return loss(SE3.compose(g, F), SE3.Ad(F).T @ m)

    M = _tensor()
    a = jax.jit(jax.grad(dense, (0, 1)))(m, M)
    b = jax.jit(jax.grad(generic, (0, 1)))(m, M)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9 * float(jnp.abs(y).max()))


def test_float32_step():
    """Twenty float32 steps of one body (tensor, `g`, `m` float32) stay on the group and within
    float32's round-off of the float64 steps."""
    kernel = lievi.DEP().kernels()[1].one_body()
    M, (g, m) = _tensor(), _states(1, seed=7)
    m = m / jnp.abs(m).max()
    step = jax.jit(lambda M, g, m: _one_step(kernel, M, g, m, 0.1))
    states = {}
    for dtype in (jnp.float32, jnp.float64):
        x = (g.astype(dtype), m.astype(dtype))
        for _ in range(20):
            *x, result, _, _ = step(M.astype(dtype), *x)
            np.testing.assert_array_equal(result, lievi.RESULTS.successful)
        states[dtype] = x
    (g32, m32), (g64, m64) = states[jnp.float32], states[jnp.float64]
    assert m32.dtype == jnp.float32
    np.testing.assert_allclose(m32, m64, rtol=0, atol=20 * ROUNDOFF_F32)
    np.testing.assert_allclose(g32, g64, rtol=0, atol=20 * ROUNDOFF_F32)
    assert float(jnp.max(SE3.membership_defect(g32))) <= 10 * ROUNDOFF_F32


def test_failures_are_reported():
    """A step that cannot converge in `max_steps` Newton iterations is
    `newton_not_converged`; one past the step bound `step_too_large`; never `successful`."""
    body = lievi.RigidBodySE3(tensor=_tensor())
    m = jnp.array([0.9, -0.6, 1.2, 0.3, 0.4, -0.8])
    one_iteration = lievi.simulate(
        body, lievi.DEP(max_steps=1), jnp.eye(4), m, h=0.5, n_steps=3, throw=False
    )
    assert int(one_iteration.result) == lievi.RESULTS.newton_not_converged
    too_large = lievi.simulate(body, lievi.DEP(), jnp.eye(4), 40 * m, h=0.5, n_steps=3, throw=False)
    assert int(too_large.result) == lievi.RESULTS.step_too_large


def test_one_body_program_is_small():
    """The step a one-body `simulate` compiles (`SE3NewtonKernel.one_body`) is a fraction
    of the batch step's program: at most 3000 HLO instructions before optimisation (the
    batch step, written as 36 scalars per body: about 7800), so an eager run's first call
    is mostly not compiling."""
    kernel = lievi.DEP().kernels()[1].one_body()
    g, m = _states(1)
    lowered = jax.jit(lambda g, m: _one_step(kernel, _tensor(), g, m, 0.1)).lower(g, m)
    text = lowered.as_text(dialect="hlo")
    instructions = sum(1 for line in text.splitlines() if " = " in line)
    assert instructions <= 3000, instructions


@pytest.mark.slow  # two reverse passes of a vmapped run compiled
def test_vmapped_simulate_equals_reference():
    """`jax.vmap(simulate)`: the one-body step batched takes the batch kernel's solve
    (`SE3DenseKernel._solve`); iterates and gradients with respect to the tensor and the
    initial momenta equal the generic path's to round-off."""
    from lievi._kernels._base import reference_path

    M, (_, m0) = _tensor(), _states(3, seed=8)

    def loss(M, m0):
        def one(m):
            body = lievi.RigidBodySE3(tensor=M)
            return lievi.simulate(body, lievi.DEP(), jnp.eye(4), m, h=0.1, n_steps=5)

        sol = jax.vmap(one)(m0)
        return jnp.sum(sol.m[:, -1] ** 2) + jnp.sum(sol.g[:, -1] * jnp.arange(4.0)), sol

    run = jax.value_and_grad(loss, (0, 1), has_aux=True)
    (_, fast), fast_grads = jax.jit(run)(M, m0)
    with reference_path():
        (_, reference), reference_grads = jax.jit(run)(M, m0)
    np.testing.assert_array_equal(fast.result, lievi.RESULTS.successful)
    np.testing.assert_allclose(fast.m, reference.m, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(fast.g, reference.g, rtol=0, atol=ROUNDOFF)
    for a, b in zip(fast_grads, reference_grads):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * float(jnp.abs(b).max()))


def test_eager_one_body_run_across_blocks(monkeypatch):
    """An eager one-body run carries the whole-array state from block to block: two
    programs, none on a new horizon, step or momentum, and a run of 9 steps (3 blocks of
    at most 4 saves) gives the first saves of a run of 13 bit for bit."""
    from lievi import _loop

    compiled = []

    def record(name, duration, **kwargs):
        if name == "/jax/core/compile/backend_compile_duration":
            compiled.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(record)
    monkeypatch.setattr(_loop, "MAX_BLOCK_SAVES", 4)
    jax.clear_caches()
    body = lievi.RigidBodySE3(tensor=_tensor(seed=5))  # values no other test compiled
    m = np.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])

    def run(n, h, m):
        return lievi.simulate(body, lievi.DEP(), np.eye(4), m, h=h, n_steps=n)

    try:
        compiled.clear()  # the system's construction aside
        short = run(9, 0.1, m)
        assert len(compiled) <= 2, compiled
        compiled.clear()
        longer = run(13, 0.1, m)
        other = run(30, 0.05, 1.1 * m)
        assert compiled == []
    finally:
        jax.monitoring.unregister_event_duration_listener(record)
        jax.clear_caches()
    for sol in (short, longer, other):
        np.testing.assert_array_equal(sol.result, lievi.RESULTS.successful)
    np.testing.assert_array_equal(longer.g[:10], short.g)
    np.testing.assert_array_equal(longer.m[:10], short.m)
