"""Shared test problems and tolerances (stated once, here)."""

import equinox as eqx
import jax
import jax.monitoring
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import lievi

# float64 tolerances
ROUNDOFF = 1e-12  # conserved quantities, DEL residual, Poisson defect, group identities
# float32 tolerances (values only; ~1e3 ulps)
ROUNDOFF_F32 = 1e-4


def hlw_problem():
    """Hairer–Lubich–Wanner rigid body (docs/theory/test-problems.md)."""
    body = lievi.RigidBody(jnp.array([2.0, 1.0, 2.0 / 3.0]))
    m0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
    return body, jnp.eye(3), m0


class GenericPreprocessed(lievi.PreprocessedMoserVeselov):
    """The preprocessed method on the generic path: a subclass runs its own step (its
    per-run `init` under `jax.vmap`), never its parent's kernel (`own_step`)."""


def random_rotation(rng, n):
    q, r = np.linalg.qr(rng.normal(size=(n, n)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return jnp.asarray(q)


def random_generalized_body(rng, n):
    """A random generalized rigid body on SO(n) with Λᵢ + Λⱼ > 0, a random state."""
    Lambda = jnp.asarray(rng.uniform(0.5, 2.0, size=n))
    body = lievi.GeneralizedRigidBody(Lambda)
    d = n * (n - 1) // 2
    m0 = jnp.asarray(rng.normal(size=d))
    return body, random_rotation(rng, n), m0


# Every integrator of the core library, for parametrize.
INTEGRATORS = (lievi.DEP(chart="exp"), lievi.DEP(chart="cayley"))
INTEGRATOR_IDS = ("dep-exp", "dep-cayley")
# The same, the exp chart's case marked `extended`: for checks whose cayley case is the one
# kept in the default suite.
INTEGRATORS_EXP_EXTENDED = (
    pytest.param(INTEGRATORS[0], marks=pytest.mark.extended, id=INTEGRATOR_IDS[0]),
    pytest.param(INTEGRATORS[1], id=INTEGRATOR_IDS[1]),
)


@eqx.filter_jit
def final_state(system, integrator, g0, m0, h, n):
    """`(g, m, all steps successful)` after `n` steps of size `h` (both traced: one compile serves every step size)."""

    def body(_, state):
        g, m, ok = state
        g, m, info = integrator.step(system, g, m, h)
        return g, m, ok & (info.result == lievi.RESULTS.successful)

    return jax.lax.fori_loop(0, n, body, (g0, m0, jnp.asarray(True)))


def dop853_final(rhs, y0, T):
    """The state at `T` of `y' = rhs(y)` (a JAX function of a flat state) from `y0`, by
    SciPy's DOP853 at rtol = atol = 1e-13: the reference of the order tests."""
    sol = solve_ivp(
        lambda t, y: np.asarray(rhs(jnp.asarray(y))),
        (0.0, T),
        np.asarray(y0),
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    assert sol.success
    return jnp.asarray(sol.y[:, -1])


def assert_kernel_matches_generic(fast, generic, fast_grads, generic_grads, iterates, gradients):
    """A kernel run and its generic path's (`Solution`s and gradients): every body
    successful, iterates to `iterates` (momenta relative to their scale), gradients to
    `gradients` relative, and no gradient identically zero."""
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_array_equal(generic.result, 0)
    scale = float(np.max(np.abs(generic.m)))
    np.testing.assert_allclose(fast.m, generic.m, rtol=0, atol=iterates * scale)
    np.testing.assert_allclose(fast.g, generic.g, rtol=0, atol=iterates)
    for a, b in zip(fast_grads, generic_grads):
        assert float(np.max(np.abs(b))) > 0
        np.testing.assert_allclose(a, b, rtol=gradients, atol=gradients * float(np.max(np.abs(b))))


_COMPILING: list[list] = []  # the open `programs_compiled` records


def _record_compile(name, duration, **kwargs):
    if name == "/jax/core/compile/backend_compile_duration":
        for names in _COMPILING:
            names.append(kwargs.get("fun_name"))


jax.monitoring.register_event_duration_secs_listener(_record_compile)


def programs_compiled(call) -> list:
    """The names of the XLA programs compiled while `call()` runs, its result ready (a
    count of compilations, not a timing)."""
    names: list = []
    _COMPILING.append(names)
    try:
        jax.block_until_ready(call())
    finally:
        _COMPILING.remove(names)
    return names
