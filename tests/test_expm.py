"""The small-matrix `expm` and `φ₁` of `lievi._groups._expm` against scipy (an independent
implementation), at norms that take from no doubling to six, batched with elements that
need different counts (the loop is masked per element and skipped when none needs it),
and differentiated in both modes through the masked loop.

`φ₁(A) = Σ Aⁿ/(n+1)!` is the top-right block of `expm([[A, I], [0, 0]])` (the reference
below, evaluated by scipy on the host); `MatrixLieGroup.dexp` is `φ₁(ad_x)`.
"""

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from lievi._groups._expm import expm, phi1

# ∞-norms 0 (none), 0.3 (none), 3 (3 doublings) and 25 (6): each row of the batch below.
NORMS = (0.0, 0.3, 3.0, 25.0)
# Relative to the size of φ₁(A) (or exp(A)); at ‖A‖ = 25 the doublings amplify round-off
# by about the condition of the problem, ‖A‖.
RTOL = 1e-13


def _matrices(n=6, seed=0):
    A = np.random.default_rng(seed).standard_normal((len(NORMS), n, n))
    A /= np.abs(A).sum(-1).max(-1)[:, None, None]
    return A * np.array(NORMS)[:, None, None]


def _phi1_reference(A):
    n = A.shape[-1]
    block = np.zeros((2 * n, 2 * n))
    block[:n, :n], block[:n, n:] = A, np.eye(n)
    return scipy.linalg.expm(block)[:n, n:]


def _close(actual, expected):
    scale = np.abs(expected).max()
    np.testing.assert_allclose(actual, expected, rtol=0, atol=RTOL * scale)


def test_phi1_and_expm_against_scipy_batched_and_one_by_one():
    A = _matrices()
    batched_phi, batched_exp = jax.jit(phi1)(A), jax.jit(expm)(A)
    for k in range(len(NORMS)):
        _close(np.asarray(batched_phi[k]), _phi1_reference(A[k]))
        _close(np.asarray(batched_exp[k]), scipy.linalg.expm(A[k]))
        # One matrix alone (the loop skipped for the unscaled ones): the same values.
        _close(np.asarray(phi1(jnp.asarray(A[k]))), _phi1_reference(A[k]))
    # φ₁(A)·A = exp(A) − I, an identity the two functions share no code for but `_scaled`.
    for k in range(len(NORMS)):
        _close(np.asarray(batched_phi[k]) @ A[k], np.asarray(batched_exp[k]) - np.eye(6))


@pytest.mark.parametrize("norm", [0.3, 3.0])
def test_phi1_reverse_mode_through_the_masked_loop_equals_forward_mode(norm):
    A = jnp.asarray(_matrices()[NORMS.index(norm)])
    W = jnp.asarray(np.random.default_rng(1).standard_normal((6, 6)))

    def f(A):
        return jnp.sum(W * phi1(A))

    reverse = jax.grad(f)(A)
    forward = jax.jacfwd(f)(A)
    np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-12)
    # And against a central difference of the scipy reference along one direction.
    D = jnp.asarray(np.random.default_rng(2).standard_normal((6, 6)))
    eps = 1e-6
    fd = (
        np.sum(W * _phi1_reference(np.asarray(A + eps * D)))
        - np.sum(W * _phi1_reference(np.asarray(A - eps * D)))
    ) / (2 * eps)
    np.testing.assert_allclose(float(jnp.sum(reverse * D)), fd, rtol=1e-7)


def test_phi1_float32():
    A = _matrices()[:3]
    actual = np.asarray(phi1(jnp.asarray(A, jnp.float32)))
    for k in range(3):
        expected = _phi1_reference(A[k])
        np.testing.assert_allclose(actual[k], expected, rtol=0, atol=1e-5 * np.abs(expected).max())


def _primitives(jaxpr):
    """The names of the primitives of `jaxpr` and of every jaxpr nested in it."""
    names = set()
    for eqn in jaxpr.eqns:
        names.add(eqn.primitive.name)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            names |= _primitives(sub)
    return names


@pytest.mark.parametrize("f", [expm, phi1], ids=["expm", "phi1"])
def test_the_doubling_loop_stays_a_branch_under_vmap(f):
    """Under `jax.vmap` the test "any element scaled" is over the whole batch, so the
    doubling loop stays behind a `cond` (skipped at run time when no element of the
    batch needs it) instead of a `select` that runs it for every element; the values are
    those of each element alone (the loop is masked per element), here with elements that
    need none and elements that need six doublings in one batch."""
    A = _matrices()
    jaxpr = jax.make_jaxpr(jax.vmap(f))(jnp.asarray(A)).jaxpr
    assert "cond" in _primitives(jaxpr)
    batched = np.asarray(jax.vmap(f)(jnp.asarray(A)))
    for a, value in zip(A, batched):
        expected = _phi1_reference(a) if f is phi1 else scipy.linalg.expm(a)
        _close(value, expected)
        np.testing.assert_array_equal(value, np.asarray(f(jnp.asarray(a))))
    # A batch in which no element needs a doubling runs the same program to the same values.
    small = A[:2]
    np.testing.assert_array_equal(
        np.asarray(jax.vmap(f)(jnp.asarray(small))), np.asarray(f(jnp.asarray(small)))
    )
