"""Structure-of-arrays arithmetic shared by the fast kernels.

A vector is a tuple of arrays (one per component, each `(B,)` with the batch minor, or
scalars for one body), a matrix a tuple of rows. Everything here is elementwise, so XLA
fuses it into long vectorised loops; there is no library trigonometry (on CPU `jnp.sin`
is a scalar libm call, ~12× slower than a 12-term polynomial in the same loop, measured):
the trigonometric coefficients of the SO(3) charts are power series in `u = φ²`,
`φ = θ/2`, accurate to round-off for `θ ≤ π` (docs/theory/closed-forms.md).
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from .._groups._series import horner  # noqa: F401  (the kernels' Horner, written once)

# Power-series coefficients in u = φ², φ = θ/2. Eleven terms: the first omitted term is
# below 1e-18 at φ = π/2 (θ = π).
N_TERMS = 11
S_SERIES = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(N_TERMS))  # sin φ / φ
C_SERIES = tuple((-1) ** k / math.factorial(2 * k) for k in range(N_TERMS))  # cos φ
P_SERIES = tuple((-1) ** (k + 1) * 2 * k / math.factorial(2 * k + 1) for k in range(1, N_TERMS + 1))


def horner_with_derivative(coefficients, u):
    value, derivative = jnp.zeros_like(u), jnp.zeros_like(u)
    for c in reversed(coefficients):
        derivative = derivative * u + value
        value = value * u + c
    return value, derivative


def cross(x, y):
    return (x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0])


def dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def det3(J):
    """`det J` for a 3×3 matrix given as nested tuples of arrays."""
    (a, b, c), (d, e, f), (g, h, i) = J
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def solve3(J, r, divide_each: bool = False):
    """`J⁻¹ r` for a 3×3 matrix given as nested tuples of arrays (Cramer's rule).

    By default `1/det J` is computed once: XLA stores a division's result rather than
    repeat it in each consumer, so that is one more loop over the batch, which evaluates
    all of `J`. With `divide_each`, each component divides by `det J` itself. Use it where
    `J` costs much more to evaluate than a division, as on SE(3): then `J` is evaluated
    three times an iteration, not four.
    """
    (a, b, c), (d, e, f), (g, h, i) = J
    # Cofactors: the adjugate's entries.
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    D, E, F = c * h - b * i, a * i - c * g, b * g - a * h
    G, H, I = b * f - c * e, c * d - a * f, a * e - b * d
    det = a * A + b * B + c * C
    numerators = (
        A * r[0] + D * r[1] + G * r[2],
        B * r[0] + E * r[1] + H * r[2],
        C * r[0] + F * r[1] + I * r[2],
    )
    if divide_each:
        return tuple(n / det for n in numerators)
    inv_det = 1 / det
    return tuple(n * inv_det for n in numerators)


def max_abs(x):
    """`‖x‖_∞` per body over every component of `x` (a tuple of arrays, any length: 3 on
    SO(3), 6 on SE(3) — a norm of the first three alone would let an SE(3) step's
    tolerance and convergence test ignore the linear momentum and its residual)."""
    norm = jnp.abs(x[0])
    for e in x[1:]:
        norm = jnp.maximum(norm, jnp.abs(e))
    return norm


def inverse3(M):
    (a, b, c), (d, e, f), (g, h, i) = M
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    D, E, F = c * h - b * i, a * i - c * g, b * g - a * h
    G, H, I = b * f - c * e, c * d - a * f, a * e - b * d
    # A division: stored once, not recomputed by the nine entries that read it.
    inv = 1 / (a * A + b * B + c * C)
    return ((A * inv, D * inv, G * inv), (B * inv, E * inv, H * inv), (C * inv, F * inv, I * inv))


def flat(X):
    return [e for row in X for e in row]


def nested(flat):
    return tuple(tuple(flat[3 * i : 3 * i + 3]) for i in range(3))


def matmul(X, Y):
    return tuple(
        tuple(X[i][0] * Y[0][j] + X[i][1] * Y[1][j] + X[i][2] * Y[2][j] for j in range(3))
        for i in range(3)
    )


def block(A, i, j):
    """The 3×3 block `(i, j)` of a 6×6 nested tuple."""
    return tuple(tuple(A[3 * i + k][3 * j + l] for l in range(3)) for k in range(3))


def entries(X, component_major: bool = False):
    """A `(…, n, n)` array (`(n, n, …)` if `component_major`) as an n×n nested tuple of
    `(…)` arrays (`(B,)` or scalars)."""
    n = X.shape[0 if component_major else -1]
    if component_major:
        return tuple(tuple(X[i, j] for j in range(n)) for i in range(n))
    return tuple(tuple(X[..., i, j] for j in range(n)) for i in range(n))


def matrix(X):
    """`entries`' inverse: an n×n nested tuple of `(…)` arrays as a `(…, n, n)` array."""
    return jnp.stack([jnp.stack(row, -1) for row in X], -2)


def component_major(X):
    """A `(…, n, n)` array as `(n, n, …)`: `X[i][j]` is then entry `(i, j)`, as in a nested
    tuple, a contiguous `(B,)` array (or a scalar) read where it is used (slices fuse into
    their consumers; sliced out once, each was a kernel of its own in XLA's program)."""
    return jnp.moveaxis(X, (-2, -1), (0, 1))


def cramer_inverse(X):
    """The inverse of `(…, 3, 3)` arrays by Cramer's rule (`inverse3`'s), as whole-array
    operations: the adjugate's columns are cross products of the rows."""
    r0, r1, r2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
    adjugate = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], -1)
    det = jnp.sum(r0 * adjugate[..., :, 0], -1)
    return adjugate / det[..., None, None]


def rotate_rows(g, x, a, b):
    """`g F` row by row, `F = 1 + a x̂ + b (xxᵀ − t 1)` (`t = |x|²`; the SO(3) increment of
    a step, `a`, `b` its chart's coefficients); `g` is 9 entries (row-major) or only some
    of its rows (3 a row, e.g. the advected `Γᵀ = e₃ᵀg`)."""
    t = dot(x, x)
    X = (0, -x[2], x[1], x[2], 0, -x[0], -x[1], x[0], 0)
    D = [a * X[3 * i + j] + b * x[i] * x[j] for i in range(3) for j in range(3)]
    for i in range(3):
        D[4 * i] = D[4 * i] - b * t
    return times_increment(g, D)


def times_increment(g, D):
    """`g F` for a step's increment `F = 1 + D` given as `D` (9 entries, row-major), as
    `g + g D`: the identity's share is added last and exactly, so a step rounds `g` by
    about one ulp where the three products of `g F` round it by about three (the drift of
    `gᵀg` off the identity over many steps is this rounding's random walk: measured
    1.0–1.1e-13 → 5.3–6.4e-14 after 10⁵ steps). `g` as in `rotate_rows`."""
    return tuple(
        g[3 * i + j] + (g[3 * i] * D[j] + g[3 * i + 1] * D[3 + j] + g[3 * i + 2] * D[6 + j])
        for i in range(len(g) // 3)
        for j in range(3)
    )
