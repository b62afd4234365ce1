"""A matrix exponential for the small matrices of Lie algebras: Taylor + scaling-squaring.

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


def expm(X: jax.Array) -> jax.Array:
    """`exp(X)` for square matrices with leading batch axes."""
    n = X.shape[-1]
    eye = jnp.eye(n, dtype=X.dtype)
    norm = jnp.max(jnp.sum(jnp.abs(X), axis=-1), axis=-1)  # ∞-norm, per batch element
    # Squarings needed; the `where` keeps log2 away from 0 (and its gradient finite).
    ratio = jnp.where(norm > _TARGET_NORM, norm / _TARGET_NORM, 1.0)
    s = jnp.clip(jnp.ceil(jnp.log2(ratio)), 0, _MAX_SQUARINGS)
    s = jax.lax.stop_gradient(s)
    Y = X / (2.0**s)[..., None, None]

    # Horner: I + Y(I + Y/2(I + Y/3(...))).
    P = eye + Y / _DEGREE
    for k in range(_DEGREE - 1, 0, -1):
        P = eye + (Y @ P) / k

    def square(i, E):
        return jnp.where((i < s)[..., None, None], E @ E, E)

    return jax.lax.fori_loop(0, _MAX_SQUARINGS, square, P)
