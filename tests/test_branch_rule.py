"""The branch rule of the implicit methods: a step reported successful ends on the root
continued from `h → 0`, on the kernel path (`simulate`, `simulate_batch`) and on the
generic reference path alike, and the paths report the same result codes.

The continued root is computed independently here, by numerical continuation in the step
size: Newton on the generic residual (`jax.jacfwd`, `linalg.solve`) at `h/K, 2h/K, …, h`,
each started from the previous root. Bodies are anisotropic (moments over three decades)
and steps turn up to 3.1 rad (the exp chart's limit is π).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi._kernels._base import reference_path

BODIES = 96
CONTINUATION_STEPS, NEWTON = 96, 8
ROOT = 1e-8  # the step's root against the continued one, relative to |ξ| + h|Ω|


def _problem(seed):
    rng = np.random.default_rng(seed)
    inertia = np.exp(rng.uniform(np.log(0.05), np.log(60.0), (BODIES, 3)))
    m0 = rng.normal(size=(BODIES, 3))
    turn = rng.uniform(0.05, 3.1, BODIES)  # h|Ω|
    h = turn / np.linalg.norm(m0 / inertia, axis=1)
    return jnp.asarray(inertia), jnp.asarray(m0), jnp.asarray(h)


def _continued_root(integrator, inertia, m, h):
    """The root continued from h → 0 (NaN where the continuation folds or diverges)."""
    body = lievi.RigidBody(inertia)

    def residual_at(x, step):
        return integrator.residual(body, m, step)(x)

    def advance(x, k):
        step = h * (k + 1) / CONTINUATION_STEPS
        for _ in range(NEWTON):
            x = x - jnp.linalg.solve(jax.jacfwd(residual_at)(x, step), residual_at(x, step))
        return x, None

    x, _ = jax.lax.scan(advance, jnp.zeros(3, m.dtype), jnp.arange(CONTINUATION_STEPS))
    ok = jnp.max(jnp.abs(residual_at(x, h))) <= 1e-10 * (1 + jnp.max(jnp.abs(m)))
    return jnp.where(ok, x, jnp.nan)


@pytest.mark.parametrize(
    "integrator",
    [
        pytest.param(lievi.DEP(), marks=pytest.mark.extended),  # 18 s
        pytest.param(lievi.DEP(chart="cayley"), marks=pytest.mark.slow),
        pytest.param(lievi.MoserVeselov(), marks=pytest.mark.extended),  # 16 s
    ],
    ids=["dep-exp", "dep-cayley", "moser-veselov"],
)
def test_successful_steps_are_on_the_continued_branch(integrator):
    inertia, m0, h = _problem(3)
    continued = jax.jit(jax.vmap(lambda i, m, s: _continued_root(integrator, i, m, s)))(
        inertia, m0, h
    )

    def one_step(i, m, s):
        sol = lievi.simulate(
            lievi.RigidBody(i), integrator, jnp.eye(3), m, h=s, n_steps=1, throw=False
        )
        return sol.g[-1], sol.result

    step = jax.jit(jax.vmap(one_step))
    g_fast, code_fast = step(inertia, m0, h)
    batch = lievi.simulate_batch(
        jax.vmap(lievi.RigidBody)(inertia),
        integrator,
        jnp.broadcast_to(jnp.eye(3), (BODIES, 3, 3)),
        m0,
        h=h,
        n_steps=1,
        system_axis=0,
        throw=False,
        save=lievi.Save(every=1),
    )
    with reference_path():
        g_generic, code_generic = jax.jit(jax.vmap(one_step))(inertia, m0, h)

    # One body and the batch: the same kernel, the same codes.
    np.testing.assert_array_equal(code_fast, batch.result)
    # A successful step is on the continued root: its increment F = g₁ equals φ(ξ*) with ξ*
    # the continued root (compared as matrices: no chart inverse needed).
    chart_map = jax.vmap(_chart_map(integrator))
    expected = chart_map(continued)
    scale = 1 + np.linalg.norm(np.asarray(continued), axis=1)
    for name, g, code in (("kernel", g_fast, code_fast), ("generic", g_generic, code_generic)):
        ok = np.asarray(code) == 0
        assert ok.sum() >= BODIES // 4, f"{name}: too few successful steps to test"
        on_branch = np.isfinite(np.asarray(continued)).all(axis=1)
        assert np.all(on_branch[ok]), f"{name}: a step succeeded where no continued root exists"
        error = np.abs(np.asarray(g) - np.asarray(expected)).max(axis=(1, 2))
        bad = ok & ~(error <= ROOT * scale)
        assert not bad.any(), (
            f"{name}: successful steps off the continued root: bodies {np.flatnonzero(bad)}, "
            f"errors {error[bad]}"
        )
    # Where the generic path succeeds, so does the kernel, and conversely.
    np.testing.assert_array_equal(np.asarray(code_fast) == 0, np.asarray(code_generic) == 0)


def _chart_map(integrator):
    if isinstance(integrator, lievi.MoserVeselov):
        return lievi.SO3.cay
    return lievi.SO3.exp if integrator.chart == "exp" else lievi.SO3.cay


def test_branch_rule_reads_the_sign_of_a_tiny_determinant():
    """The rule's determinant when it is tiny: `det J` of SO(4)'s 6×6 Jacobian with
    moments 1e-3…4e-3 and h = 1e5 is about 1.3e-44, below float32's normal range, and
    `jnp.linalg.det` returns 0 for it in float32. A small step (h|ξ| ≈ 0.01) is on the
    branch; read from `det J` itself, float32 reported it `step_too_large`."""
    dtype = jnp.float32
    n = 4
    body = lievi.GeneralizedRigidBody(1e-3 * jnp.arange(1.0, n + 1, dtype=dtype))
    m0 = 1e-10 * jnp.linspace(-1, 1, n * (n - 1) // 2, dtype=dtype)
    integrator = lievi.DEP(chart="cayley")
    sol = lievi.simulate(body, integrator, jnp.eye(n, dtype=dtype), m0, h=1e5, n_steps=3)
    assert sol.result == lievi.RESULTS.successful
    assert sol.m.dtype == dtype
