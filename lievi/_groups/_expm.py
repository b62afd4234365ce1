"""A matrix exponential for the small matrices of Lie algebras, and `φ₁(A) = Σ Aⁿ/(n+1)!`
(the derivative of `exp`, paper (4.3)): Taylor + scaling-squaring.

`jax.scipy.linalg.expm` picks among several Padé approximants with `lax.cond` and
squares in a data-dependent loop; differentiated inside a Newton loop it dominates compile
time. The matrices here are small (n ≤ ~16) and of moderate norm (a step's increment), so
a fixed-degree Taylor polynomial of `X / 2^s` followed by `s` squarings is as accurate,
compiles to a handful of matmuls, and differentiates cleanly in both modes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# ‖X/2^s‖ ≤ 1/2 and degree 18: truncation error 2^-19/19! ≈ 1.6e-23 relative to 1.
_DEGREE = 18
_TARGET_NORM = 0.5
# Norms up to 0.5 · 2^_MAX_SQUARINGS ≈ 1.6e4 are handled to full accuracy.
_MAX_SQUARINGS = 15


# φ₁'s Taylor degree: with ‖Y‖ ≤ 1/2 the first term left out, Y¹⁵/16!, is below 1.6e-18.
_PHI1_DEGREE = 14


def _scaled(X: jax.Array):
    """`(X / 2^s, s)` with `‖X / 2^s‖_∞ ≤ _TARGET_NORM` (`s` clipped to `_MAX_SQUARINGS`)."""
    norm = jnp.max(jnp.sum(jnp.abs(X), axis=-1), axis=-1)  # ∞-norm, per batch element
    # Squarings needed; the `where` keeps log2 away from 0 (and its gradient finite).
    ratio = jnp.where(norm > _TARGET_NORM, norm / _TARGET_NORM, 1.0)
    s = jnp.clip(jnp.ceil(jnp.log2(ratio)), 0, _MAX_SQUARINGS)
    s = jax.lax.stop_gradient(s)
    return X / (2.0**s)[..., None, None], s


@jax.custom_batching.custom_vmap
def _any_scaled(s):
    """Whether any element was scaled (`s > 0`): the test of `_unscale`'s `lax.cond`.

    Under `jax.vmap` (`simulate_batch`'s generic path vmaps `simulate`) it is the test
    over the whole batch, one unbatched boolean, so the `cond` stays a branch, skipped
    when no body needs a doubling. With JAX's own batching rule the predicate would be
    per body and the `cond` a `select` that runs the loop for every body at every call
    (measured: `DEP()` on 256 `SOn(4)` bodies took 2.1× the time per body-step,
    the retired `son_dexp.py`). The values do not change: the loop is masked per
    element."""
    return jnp.any(s > 0)


@_any_scaled.def_vmap
def _any_scaled_batched(axis_size, in_batched, s):
    del axis_size, in_batched
    return jnp.any(s > 0), False


def _unscale(step, s, carry, enter=None, leave=None):
    """`step` applied `s` times to `carry` (`s` per batch element); `enter` maps `carry`
    to the loop's state (a matrix or a pair) and `leave` maps that back, both only when
    the loop runs.

    The loop has a fixed length, masked per element, so that reverse mode differentiates
    it; it is skipped at run time when no element was scaled (`lax.cond`), as for most of
    a DEP run's increments: on one body the masked loop was most of `exp`'s and `dexp`'s
    time (about 60 % of `SOn(4).dexp`, 15 masked iterations of two 6×6 products). The
    test is `_any_scaled`, which stays one boolean under `jax.vmap`.
    """

    def masked(i, carry):
        on = (i < s)[..., None, None]
        return jax.tree.map(lambda new, old: jnp.where(on, new, old), step(carry), carry)

    def loop(carry):
        state = carry if enter is None else enter(carry)
        state = jax.lax.fori_loop(0, _MAX_SQUARINGS, masked, state)
        return state if leave is None else leave(state)

    return jax.lax.cond(_any_scaled(s), loop, lambda carry: carry, carry)


def expm(X: jax.Array) -> jax.Array:
    """`exp(X)` for square matrices with leading batch axes."""
    n = X.shape[-1]
    eye = jnp.eye(n, dtype=X.dtype)
    Y, s = _scaled(X)

    # Horner: I + Y(I + Y/2(I + Y/3(...))).
    P = eye + Y / _DEGREE
    for k in range(_DEGREE - 1, 0, -1):
        P = eye + (Y @ P) / k

    return _unscale(lambda E: E @ E, s, P)


def phi1(A: jax.Array) -> jax.Array:
    """`φ₁(A) = Σ Aⁿ/(n+1)!` (`(e^A − I)A⁻¹` where `A` is invertible) for square matrices
    with leading batch axes.

    Taylor on `Y = A/2^s`, then `s` doublings of the pair `(e^Y, φ₁(Y))`:
    `φ₁(2Y) = ½(e^Y + I) φ₁(Y)` (`e^{2Y} − I = (e^Y − I)(e^Y + I)`), `e^{2Y} = (e^Y)²`.
    For `A = ad_x` this is `dexp(x)` (`MatrixLieGroup.dexp`) on `d × d` matrices; the
    top-right block of `expm([[A, I], [0, 0]])` gives the same on `2d × 2d` ones, at about
    six times the arithmetic.
    """
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)
    Y, s = _scaled(A)

    # Horner: I + Y/2 (I + Y/3 (… (I + Y/(K+1)))), K = _PHI1_DEGREE.
    P = eye + Y / (_PHI1_DEGREE + 1)
    for k in range(_PHI1_DEGREE, 1, -1):
        P = eye + (Y @ P) / k

    def double(pair):
        E, P = pair
        return E @ E, (P + E @ P) / 2

    # `e^Y = I + Y φ₁(Y)` only where a doubling reads it.
    return _unscale(double, s, P, enter=lambda P: (eye + Y @ P, P), leave=lambda pair: pair[1])
