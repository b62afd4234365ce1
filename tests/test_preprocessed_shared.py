"""The modified moments of a batch sharing one body, fitted from a few sample trajectories
(`_integrators/_preprocessed_shared.py`), against each body's own series: the same moments
to round-off over a wide spread of energies and Casimirs, and on the kernel the same
iterates and gradients as the generic path."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import GenericPreprocessed, assert_kernel_matches_generic
from lievi._integrators._preprocessed_dmv import (
    modified_principal_moments,
    shared_modified_principal_moments,
)

ITERATES = 1e-13  # relative to the momentum scale (float64)
GRADIENTS = 1e-10
MOMENTS = 1e-13  # relative, float64
INERTIA = jnp.array([0.6, 0.8, 1.0])


def _momenta(rng, batch, dtype=jnp.float64):
    """Directions over the whole sphere (every energy per Casimir, near both stable axes
    and the separatrix) and Casimirs over four decades, within the step-size bound at
    `h = 0.1` (`h|Ω| ≤ 0.6`)."""
    directions = rng.normal(size=(batch, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return jnp.asarray(directions * np.geomspace(1e-3, 3.6, batch)[:, None], dtype)


# A triaxial body, Hairer–Lubich–Wanner's and a symmetric one; the orders' fits have 2–5
# samples.
CASES = [(INERTIA, 8), (jnp.array([2.0, 1.0, 2 / 3]), 10), (jnp.array([1.0, 1.0, 0.5]), 4)]


@pytest.mark.parametrize(("inertia", "order"), CASES)
def test_fitted_moments_equal_per_body_ones(inertia, order):
    m0s = _momenta(np.random.default_rng(order), 64)
    h = jnp.linspace(0.05, 0.1, 64)  # a step per body: h enters only through h^(2k)
    per_body = jax.vmap(lambda m, h: modified_principal_moments(inertia, m, h, order))(m0s, h)
    fitted = shared_modified_principal_moments(inertia, m0s, h, order)
    # The modification is visible (so equal moments are a check of the fit).
    assert float(jnp.max(jnp.abs(per_body / inertia - 1))) > 1e-3
    np.testing.assert_allclose(fitted, per_body, rtol=MOMENTS, atol=0)


def test_fitted_moments_float32():
    m0s = _momenta(np.random.default_rng(0), 64, jnp.float32)
    inertia = INERTIA.astype(jnp.float32)
    h = jnp.float32(0.1)
    per_body = jax.vmap(lambda m: modified_principal_moments(inertia, m, h, 8))(m0s)
    fitted = shared_modified_principal_moments(inertia, m0s, h, 8)
    assert fitted.dtype == jnp.float32
    np.testing.assert_allclose(fitted, per_body, rtol=20 * np.finfo(np.float32).eps, atol=0)


@pytest.mark.extended  # 15 s
def test_shared_body_kernel_equals_generic_path():
    """Iterates and gradients (inertia, `m0`) of a batch sharing one body, larger than the
    fit's samples, on the kernel (fitted moments) and on the generic path (each body's)."""
    m0s = _momenta(np.random.default_rng(1), 6)
    g0s = jnp.broadcast_to(jnp.eye(3), (6, 3, 3))

    def run(integrator):
        def loss(inertia, m0s):
            sol = lievi.simulate_batch(
                lievi.RigidBody(inertia), integrator, g0s, m0s, h=0.1, n_steps=10
            )
            value = jnp.sum(sol.m[:, -1] ** 2) + jnp.sum(sol.g[:, -1] * jnp.arange(3))
            return value, sol

        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))(INERTIA, m0s)

    (_, fast), fast_grads = run(lievi.PreprocessedMoserVeselov(8))
    (_, generic), generic_grads = run(GenericPreprocessed(8))
    assert_kernel_matches_generic(fast, generic, fast_grads, generic_grads, ITERATES, GRADIENTS)
