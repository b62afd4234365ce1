"""NaN-safe scalar series of the SO(3) and SE(3) closed forms (θ² as the argument).

Each coefficient is its exact expression away from θ = 0 and a Taylor series near it,
selected with the "double where" (the unused branch gets a safe input), so that values
and reverse-mode derivatives are finite at the identity (docs/theory/closed-forms.md).
"""

from __future__ import annotations

import math
from fractions import Fraction

import jax.numpy as jnp


def small_threshold(dtype) -> float:
    # Taylor series below are exact to O(θ¹⁰); the switch point keeps the truncation
    # error and the cancellation error of the exact forms both near machine epsilon.
    return 1e-3 if jnp.finfo(dtype).bits >= 64 else 1e-1


def series_or_exact(theta2, exact, coefficients):
    """`exact(θ²)` away from 0, the power series `Σ c_k θ^{2k}` near 0, safe for AD."""
    small = theta2 < small_threshold(theta2.dtype)
    safe = jnp.where(small, jnp.ones_like(theta2), theta2)
    series = jnp.zeros_like(theta2)
    for c in reversed(coefficients):
        series = series * theta2 + c
    return jnp.where(small, series, exact(safe))


def sinc(t2):  # sin θ / θ
    return series_or_exact(
        t2,
        lambda s: jnp.sin(jnp.sqrt(s)) / jnp.sqrt(s),
        (1, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880),
    )


def cosc(t2):  # (1 − cos θ) / θ² = 2 sin²(θ/2) / θ², written without cancellation
    return series_or_exact(
        t2,
        lambda s: 2 * jnp.sin(jnp.sqrt(s) / 2) ** 2 / s,
        (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800),
    )


def sinc3(t2):  # (θ − sin θ) / θ³
    return series_or_exact(
        t2,
        lambda s: (jnp.sqrt(s) - jnp.sin(jnp.sqrt(s))) / (s * jnp.sqrt(s)),
        (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800),
    )


def dexpinv_coefficient(t2):  # (1 − (θ/2) cot(θ/2)) / θ²
    def exact(s):
        half = jnp.sqrt(s) / 2
        sin = jnp.sin(half)
        # dexpinv is singular at θ = 2πk (k ≥ 1): there sin(θ/2) is round-off, and the
        # quotient would be a huge finite number (~1e16); report it as non-finite.
        singular = jnp.abs(sin) <= 4 * jnp.finfo(s.dtype).eps * half
        value = (1 - half * jnp.cos(half) / jnp.where(singular, 1.0, sin)) / s
        return jnp.where(singular, jnp.inf, value)

    return series_or_exact(t2, exact, (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160))


def bernoulli_terms(degree: int) -> tuple[float, ...]:
    """`B_k/k!` for `k = 0 … degree`: the coefficients of `dexp⁻¹_x = Σ B_k/k! ad_xᵏ`
    (Bernoulli numbers with `B_1 = −1/2`; Hairer–Lubich–Wanner, *Geometric Numerical
    Integration*, §III.4, Lemma 4.2), from `Σ_{j≤k} C(k+1, j) B_j = 0`, exact in rationals."""
    if not isinstance(degree, int) or isinstance(degree, bool) or degree < 0:
        raise ValueError(
            f"`degree` must be an integer ≥ 0 (the last power of ad kept), got {degree!r}."
        )
    numbers = [Fraction(1)]
    for k in range(1, degree + 1):
        numbers.append(-sum(math.comb(k + 1, j) * numbers[j] for j in range(k)) / (k + 1))
    return tuple(float(b / math.factorial(k)) for k, b in enumerate(numbers))


def truncated_dexpinv_terms(degree: int) -> tuple[float, ...]:
    """The coefficients in `θ²` of the SO(3) `dexpinv` coefficient of the series truncated
    after `ad_x^degree`: on so(3) `x̂³ = −θ² x̂`, so `Σ_{k≤degree} B_k/k! x̂ᵏ =
    1 − x̂/2 + c(θ²) x̂²` with `c = Σ_j B_{2j}/(2j)! (−θ²)^{j−1}` (`j = 1 … ⌊degree/2⌋`), the
    first terms of the exact `(1 − (θ/2)cot(θ/2))/θ²`: `1/12 + θ²/720 + θ⁴/30240 + …`."""
    terms = bernoulli_terms(degree)
    return tuple(terms[2 * j] * (-1) ** (j - 1) for j in range(1, degree // 2 + 1))


def horner(coefficients, t):
    """`Σ c_k tᵏ` by Horner's rule (`0` for no coefficients)."""
    value = jnp.zeros_like(t)
    for c in reversed(coefficients):
        value = value * t + c
    return value


def dot(x, y):
    return jnp.sum(x * y, axis=-1)


def outer(x, y):
    return x[..., :, None] * y[..., None, :]
