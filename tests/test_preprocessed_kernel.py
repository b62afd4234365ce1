"""`PreprocessedMoserVeselov` on the Moser–Veselov batch kernel: each body's modified
moments from its own `m0` in the run's set-up, against the generic path (its `init` under
`jax.vmap`, then `MoserVeselov`'s step on the modified body) to round-off, gradients
included; the prepared method's own check of the trajectory stays where it was."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import GenericPreprocessed, assert_kernel_matches_generic
from lievi._kernels._base import reference_path

ITERATES = 1e-13  # relative to the momentum scale (float64)
GRADIENTS = 1e-10
INERTIA = jnp.array([0.6, 0.8, 1.0])
M0S = jnp.array([[1.8, 0.4, -0.9], [0.3, -1.1, 0.7], [-0.5, 0.2, 1.4]])
G0S = jnp.broadcast_to(jnp.eye(3), (3, 3, 3))
H, STEPS = jnp.array([0.1, 0.07, 0.12]), 10  # a step per body


def _loss(integrator):
    """The final state of a batch of three bodies (per-body moments and steps) and the
    gradient of a loss of it with respect to the moments and `m0`."""

    def loss(inertias, m0s):
        bodies = jax.vmap(lievi.RigidBody)(inertias)
        sol = lievi.simulate_batch(bodies, integrator, G0S, m0s, h=H, n_steps=STEPS, system_axis=0)
        value = jnp.sum(sol.m[:, -1] ** 2) + jnp.sum(sol.g[:, -1] * jnp.arange(3))
        return value, sol

    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))


@pytest.mark.extended  # 23 s
def test_kernel_equals_generic_path():
    inertias = jnp.stack([INERTIA, INERTIA[::-1] * 1.2, INERTIA * 0.9])
    integrator = lievi.PreprocessedMoserVeselov(8)
    (_, fast), fast_grads = _loss(integrator)(inertias, M0S)
    (_, generic), generic_grads = _loss(GenericPreprocessed(8))(inertias, M0S)
    assert_kernel_matches_generic(fast, generic, fast_grads, generic_grads, ITERATES, GRADIENTS)


def test_has_fast_path_on_principal_moments_only():
    integrator = lievi.PreprocessedMoserVeselov(8)
    assert lievi.advanced.has_fast_path(lievi.RigidBody(INERTIA), integrator)
    bodies = jax.vmap(lievi.RigidBody)(jnp.stack([INERTIA, INERTIA]))
    assert lievi.advanced.has_fast_path(bodies, integrator, system_axis=0)
    # A full tensor, a subclass (its own step) and the reference path take the generic step.
    assert not lievi.advanced.has_fast_path(lievi.RigidBody(jnp.diag(INERTIA)), integrator)
    assert not lievi.advanced.has_fast_path(lievi.RigidBody(INERTIA), GenericPreprocessed(8))
    with reference_path():
        assert not lievi.advanced.has_fast_path(lievi.RigidBody(INERTIA), integrator)


@pytest.mark.extended  # 10 s
def test_one_body_runs_on_the_kernel_its_own_trajectory():
    """`simulate` of a copy prepared for another trajectory runs its own (the run's set-up
    prepares it from its `m0`), on the kernel; `step` of that copy on a momentum off its
    trajectory is still `invalid_input`."""
    body, m0 = lievi.RigidBody(INERTIA), M0S[0]
    method = lievi.PreprocessedMoserVeselov(6)
    prepared = method.prepare(body, M0S[1], 0.1)
    run = lambda integrator: lievi.simulate(  # noqa: E731
        body, integrator, jnp.eye(3), m0, h=0.1, n_steps=4, throw=False
    )
    other, fresh = run(prepared), run(method)
    assert int(other.result) == 0
    np.testing.assert_array_equal(other.m, fresh.m)
    np.testing.assert_allclose(run(GenericPreprocessed(6)).m, fresh.m, rtol=0, atol=1e-14)
    _, _, info = prepared.step(body, jnp.eye(3), M0S[1], jnp.asarray(0.1))
    assert int(info.result) == 0
    _, _, info = prepared.step(body, jnp.eye(3), m0, jnp.asarray(0.1))
    assert int(info.result) == lievi.RESULTS.invalid_input


@pytest.mark.extended  # 7 s
def test_a_step_past_the_bound_fails_as_on_the_generic_path():
    """The step-size check is on the body's own moments (the generic `step_too_large`),
    not the modified ones: the same body fails, at the same step, on both paths."""
    momenta = M0S.at[1].set(jnp.array([0.0, 40.0, 0.0]))  # h|Ω| = 5 on I₂ = 0.8
    body = lievi.RigidBody(INERTIA)

    def run(integrator):
        return lievi.simulate_batch(
            body, integrator, G0S, momenta, h=0.1, n_steps=3, save=lievi.Save(), throw=False
        )

    fast, generic = run(lievi.PreprocessedMoserVeselov(6)), run(GenericPreprocessed(6))
    assert int(fast.result[1]) == lievi.RESULTS.step_too_large
    np.testing.assert_array_equal(fast.result, generic.result)
    np.testing.assert_array_equal(fast.stats["failed_step"], generic.stats["failed_step"])
    np.testing.assert_allclose(fast.m[0], generic.m[0], rtol=0, atol=1e-13)
