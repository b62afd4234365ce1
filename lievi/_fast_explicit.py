"""Fast batched steps of the explicit rigid-body integrators on SO(3): splitting and RK4.

The structure-of-arrays counterparts of `LiePoissonSplitting` (`_splitting.py`, paper §6)
and `RK4` (`_rk4.py`) for a rigid body with principal moments `I`, as `_fast_so3.py` is
for `DEP`: every component its own `(B,)` array (batch minor), closed forms, no batched
3×3 matrix products. They compute the same iterates as the per-body methods to round-off
(the tests compare them).

The splitting's sub-flows are rotations by angles `α = f h Π_p / I_p`; on CPU `jnp.sin`
and `jnp.cos` are scalar library calls, several times slower than the rest of the step
(measured, see `_fast_so3.py`), so `sincos` below evaluates both by a Cody–Waite
reduction to `|r| ≤ π/4` and two Taylor polynomials, accurate to about one ulp for
`|α| ≲ 10⁴` in float32 and far beyond in float64 (the tests compare with `jnp.sin`).
"""

from __future__ import annotations

import decimal
import math

import jax.numpy as jnp

from ._results import RESULTS


def _pi_over_two_parts():
    """`π/2 = P1 + P2 + P3` with 12-bit `P1`, `P2` (so `k·P1`, `k·P2` are exact in float32
    for `|k| < 2¹²` and in float64 far beyond) and `P3` the rest, rounded."""
    decimal.getcontext().prec = 60
    half_pi = decimal.Decimal("3.14159265358979323846264338327950288419716939937510582097494") / 2
    p1 = decimal.Decimal(round(half_pi * 2**11)) / 2**11
    p2 = decimal.Decimal(round((half_pi - p1) * 2**23)) / 2**23
    return float(p1), float(p2), float(half_pi - p1 - p2)


_P1, _P2, _P3 = _pi_over_two_parts()
# Taylor coefficients in u = r² for sin r / r and cos r; nine terms each: the first omitted
# term is below 1e-17 (relative) at |r| = π/4.
_SIN = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(9))
_COS = tuple((-1) ** k / math.factorial(2 * k) for k in range(9))


def _horner(coefficients, u):
    value = jnp.full_like(u, coefficients[-1])
    for c in reversed(coefficients[:-1]):
        value = value * u + c
    return value


def sincos(x):
    """`(sin x, cos x)` elementwise, by range reduction and polynomials (no libm calls)."""
    k = jnp.round(x * (2 / math.pi))
    r = ((x - k * _P1) - k * _P2) - k * _P3
    u = r * r
    s, c = r * _horner(_SIN, u), _horner(_COS, u)
    # x = r + kπ/2: quadrant q = k mod 4 rotates (s, c) by q quarter turns.
    q = jnp.mod(k, 4)
    odd = (q == 1) | (q == 3)
    sin, cos = jnp.where(odd, c, s), jnp.where(odd, s, c)
    sin = jnp.where(q >= 2, -sin, sin)
    cos = jnp.where((q == 1) | (q == 2), -cos, cos)
    return sin, cos


def _finite_result(Pi, g):
    finite = jnp.isfinite(Pi[0])
    for x in (*Pi[1:], *g):
        finite = finite & jnp.isfinite(x)
    return jnp.where(finite, RESULTS.successful, RESULTS.nonfinite).astype(jnp.int32)


def _rotate_about_axis(g, Pi, p: int, alpha):
    """`g ← g F`, `Π ← Fᵀ Π` for `F = exp(α ê_p)`, the rotation by `α` about axis `p`.

    With `(q, r)` the axes after `p` in cyclic order, `F e_q = cos α e_q + sin α e_r` and
    `F e_r = −sin α e_q + cos α e_r`: columns `q`, `r` of `g` and components `q`, `r` of
    `Π` change, `Π_p` (hence the angle of the sub-flow) does not.
    """
    q, r = (p + 1) % 3, (p + 2) % 3
    s, c = sincos(alpha)
    g = list(g)
    for i in range(3):
        gq, gr = g[3 * i + q], g[3 * i + r]
        g[3 * i + q], g[3 * i + r] = c * gq + s * gr, c * gr - s * gq
    Pi = list(Pi)
    Pi[q], Pi[r] = c * Pi[q] + s * Pi[r], c * Pi[r] - s * Pi[q]
    return tuple(g), tuple(Pi)


def splitting_step(g, Pi, h_over_inertia):
    """One `LiePoissonSplitting` step: axes 0, 1 (h/2), 2 (h), 1, 0 (h/2), as `_splitting.py`.

    `g`: 9 arrays (row-major), `Pi`: 3 arrays, `h_over_inertia`: `h/I_p`, 3 arrays or
    scalars. Returns `(g_next, Pi_next, result)`.
    """
    for p, fraction in ((0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5)):
        g, Pi = _rotate_about_axis(g, Pi, p, fraction * h_over_inertia[p] * Pi[p])
    return g, Pi, _finite_result(Pi, g)


def rk4_step(g, Pi, h, inverse_inertia):
    """One `RK4` step on `ṁ = Π × Ω`, `ġ = g Ω̂`, `Ω = I⁻¹Π` (`_rk4.py`), component-wise.

    `h`: the step (array or scalar), `inverse_inertia`: `1/I_p`, 3 arrays or scalars.
    """

    def field(g, Pi):
        w = tuple(Pi[i] * inverse_inertia[i] for i in range(3))
        dPi = (Pi[1] * w[2] - Pi[2] * w[1], Pi[2] * w[0] - Pi[0] * w[2], Pi[0] * w[1] - Pi[1] * w[0])
        # (g Ω̂)_{ij} = Σ_k g_ik Ω̂_kj, Ω̂ = [[0, −w2, w1], [w2, 0, −w0], [−w1, w0, 0]].
        dg = []
        for i in range(3):
            g0, g1, g2 = g[3 * i], g[3 * i + 1], g[3 * i + 2]
            dg += [g1 * w[2] - g2 * w[1], g2 * w[0] - g0 * w[2], g0 * w[1] - g1 * w[0]]
        return tuple(dg), dPi

    def axpy(a, k, y):
        return tuple(yi + a * ki for yi, ki in zip(y, k))

    k1 = field(g, Pi)
    k2 = field(axpy(h / 2, k1[0], g), axpy(h / 2, k1[1], Pi))
    k3 = field(axpy(h / 2, k2[0], g), axpy(h / 2, k2[1], Pi))
    k4 = field(axpy(h, k3[0], g), axpy(h, k3[1], Pi))

    def combine(y, a, b, c, e):
        return tuple(yi + h / 6 * (ai + 2 * bi + 2 * ci + ei) for yi, ai, bi, ci, ei in zip(y, a, b, c, e))

    g_next = combine(g, k1[0], k2[0], k3[0], k4[0])
    Pi_next = combine(Pi, k1[1], k2[1], k3[1], k4[1])
    return g_next, Pi_next, _finite_result(Pi_next, g_next)
