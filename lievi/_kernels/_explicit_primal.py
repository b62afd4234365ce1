"""The arithmetic of the explicit rigid-body steps on SO(3) (splitting and RK4), as
structure of arrays: the primal computations that the kernels (`_explicit.py`) run and
whose tangents `_explicit_adjoints.py` writes by hand.

The splitting's sub-flows are rotations by angles `α = f h Π_p / I_p`; on CPU `jnp.sin`
and `jnp.cos` are scalar library calls, several times slower than the rest of the step
(measured, see `_kernels/_so3.py`), so `sincos` below evaluates both by a Cody–Waite
reduction to `|r| ≤ π/4` and polynomials of degree 15 and 14, accurate to about one ulp
for `|α| ≲ 10⁴` in float32 and far beyond in float64 (the tests compare with `jnp.sin`).
"""

from __future__ import annotations

import decimal
import math

import jax.numpy as jnp

from ._base import materialise, ones
from ._soa import times_increment

_HALF_PI = decimal.Decimal("3.14159265358979323846264338327950288419716939937510582097494") / 2


def _pi_over_two_parts(bits: int, count: int):
    """`π/2` as `count` parts: each but the last with `bits` significant bits (so `k·P` is
    exact while `k` has at most 24 − `bits` bits in float32, 53 − `bits` in float64), the
    last the rest, rounded."""
    decimal.getcontext().prec = 60
    parts, rest, scale = [], _HALF_PI, bits - 1
    for _ in range(count - 1):
        part = decimal.Decimal(round(rest * 2**scale)) / 2**scale
        parts.append(float(part))
        rest, scale = rest - part, scale + bits
    return (*parts, float(rest))


# float32: three parts, `k·P1`, `k·P2` exact for |k| < 2¹² (12-bit parts); float64: two, `k·P1`
# exact for |k| < 2²⁰ (a 33-bit part; beyond, |x| > 10⁶, the reduction keeps about one ulp of
# |x|, the size of the rounding of x itself).
_REDUCTION = {"float32": _pi_over_two_parts(12, 3), "float64": _pi_over_two_parts(33, 2)}


def _interpolating_coefficients(f, nodes: int):
    """Coefficients (lowest degree first) of the polynomial in `u` interpolating `f` at the
    Chebyshev nodes of `[0, (π/4)²]`, by exact elimination in 60-digit decimals: close to
    the best uniform approximation of that degree."""
    D = decimal.Decimal
    decimal.getcontext().prec = 60
    top = (_HALF_PI / 2) ** 2

    def cos_series(x):
        term, total, k = D(1), D(0), 0
        while abs(term) > D("1e-58"):
            total, k = total + term, k + 1
            term = -term * x * x / ((2 * k - 1) * (2 * k))
        return total

    xs = [
        top / 2 * (1 + cos_series((2 * i + 1) * 2 * _HALF_PI / (2 * nodes))) for i in range(nodes)
    ]
    rows = [[x**j if j else D(1) for j in range(nodes)] + [f(x)] for x in xs]
    for c in range(nodes):
        pivot = max(range(c, nodes), key=lambda r: abs(rows[r][c]))
        rows[c], rows[pivot] = rows[pivot], rows[c]
        for r in range(nodes):
            if r != c:
                m = rows[r][c] / rows[c][c]
                rows[r] = [a - m * b for a, b in zip(rows[r], rows[c])]
    return tuple(float(rows[i][nodes] / rows[i][i]) for i in range(nodes))


def _series(u, first):
    """`Σ_k (−u)^k / ((2k + first)! / first!)`: `sin √u / √u` (first = 1), `cos √u` (0)."""
    D = decimal.Decimal
    term, total, k = D(1), D(0), 0
    while abs(term) > D("1e-58"):
        total, k = total + term, k + 1
        term = -term * u / ((2 * k - 1 + first) * (2 * k + first))
    return total


# In u = r² for sin r / r and cos r on |r| ≤ π/4: eight coefficients each, within 6e-18 of
# the functions with the coefficients rounded to float64 (nine Taylor terms were needed for
# the same accuracy).
_SIN = _interpolating_coefficients(lambda u: _series(u, 1), 8)
_COS = _interpolating_coefficients(lambda u: _series(u, 0), 8)


def sincos(x):
    """`(sin x, cos x)` elementwise, by range reduction and polynomials (no libm calls):
    `x = r + qπ/2`, `|r| ≤ π/4`, `u = r²`; `sin r = r·S(u)` and `cos r = C(u)`, each one
    polynomial shared by both results, which pick them by `q mod 4` (`sin(r + qπ/2)` is
    `sin r`, `cos r`, `−sin r`, `−cos r`; `cos(r + qπ/2)` the next one). Selecting each
    coefficient by the parity of `q`, per result, evaluated the same two polynomials with
    a select a coefficient: 16 operations more a call, the same values bit for bit."""
    k = jnp.round(x * (2 / math.pi))
    r = x
    for part in _REDUCTION["float64" if x.dtype == jnp.float64 else "float32"]:
        r = r - k * part
    u = r * r
    sin_r, cos_r = _SIN[-1], _COS[-1]
    for s, c in zip(reversed(_SIN[:-1]), reversed(_COS[:-1])):
        sin_r, cos_r = sin_r * u + s, cos_r * u + c
    sin_r = r * sin_r
    # Integer bit operations (two's complement: `q & 3` is q mod 4 for negative q too): a
    # float `mod` is a scalar `fmod` call on CPU.
    q = k.astype(jnp.int32)
    odd, half = (q & 1) == 1, (q & 2) == 2
    sin_x = jnp.where(odd, cos_r, sin_r)
    cos_x = jnp.where(odd, sin_r, cos_r)
    # Negative: sin for q mod 4 in {2, 3}, cos for q mod 4 in {1, 2}.
    return jnp.where(half, -sin_x, sin_x), jnp.where(half != odd, -cos_x, cos_x)


def quaternion_product(a, b):
    """`a ⊗ b` for quaternions `(w, x, y, z)`: `R(a ⊗ b) = R(a) R(b)`. Entries may be Python
    zeros (an axis rotation `(cos α/2, sin α/2 e_p)` has two), whose products are left out."""

    def signed_sum(*terms):  # Σ sign·x·y over the terms whose factors are not Python zeros
        kept = [
            (sign, x * y)
            for sign, x, y in terms
            if not any(isinstance(v, float) and v == 0 for v in (x, y))
        ]
        total = kept[0][1] if kept[0][0] > 0 else -kept[0][1]
        for sign, xy in kept[1:]:
            total = total + xy if sign > 0 else total - xy
        return total

    (aw, ax, ay, az), (bw, bx, by, bz) = a, b
    return (
        signed_sum((1, aw, bw), (-1, ax, bx), (-1, ay, by), (-1, az, bz)),
        signed_sum((1, aw, bx), (1, ax, bw), (1, ay, bz), (-1, az, by)),
        signed_sum((1, aw, by), (-1, ax, bz), (1, ay, bw), (1, az, bx)),
        signed_sum((1, aw, bz), (1, ax, by), (-1, ay, bx), (1, az, bw)),
    )


def rotation_minus_identity(quaternion):
    """`R(q) − 1` for a unit quaternion `q = (w, x, y, z)`: 9 arrays, row-major."""
    w, x, y, z = quaternion
    return (
        -2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        -2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        -2 * (x * x + y * y),
    )


def matmul3(X, Y):
    """`X Y` for 3×3 matrices as 9 arrays; `X` may also be fewer rows (3 arrays a row),
    e.g. the advected row `Γᵀ`."""
    return tuple(
        X[3 * i] * Y[j] + X[3 * i + 1] * Y[3 + j] + X[3 * i + 2] * Y[6 + j]
        for i in range(len(X) // 3)
        for j in range(3)
    )


# (axis, fraction of h) of the palindromic splitting's sub-flows, as `_splitting.py`.
SUBFLOWS = ((0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5))


def splitting_primal(g, m, rate):
    """`splitting_step`'s arithmetic: `(g_next, Π_next, [(cos α_j, sin α_j)], [Π^{(j)}], F)`,
    the rotations, the momenta before and after each sub-flow (`j = 0…5`, sequentially
    rotated) and the composed increment `F = F_1⋯F_5` (9 arrays); `g_next = g F`,
    `Π_next = Fᵀ Π`."""
    one = ones(m[0])
    factors, rotations, momenta = [], [], [tuple(m)]
    for p, fraction in SUBFLOWS:
        # The half angle α/2 = (f/2)·Π_p·(h/I_p): a product. As a quotient by I_p/h it
        # was a division a sub-flow, which XLA evaluates once and stores (see
        # `materialise`): one more array written and read back per angle.
        sin_half, cos_half = materialise(sincos((0.5 * fraction) * m[p] * rate[p]), one)
        c, s = 1 - 2 * sin_half * sin_half, 2 * sin_half * cos_half
        q, r = (p + 1) % 3, (p + 2) % 3
        m = list(m)
        m[q], m[r] = c * m[q] + s * m[r], c * m[r] - s * m[q]
        rotations.append((c, s))
        momenta.append(tuple(m))
        factors.append((cos_half, *(sin_half if i == p else 0.0 for i in range(3))))
    # (q1 q2) q3 (q4 q5): the two sparse pairs first, 4 products each.
    q12, q45 = quaternion_product(*factors[:2]), quaternion_product(*factors[3:])
    quaternion = quaternion_product(quaternion_product(q12, factors[2]), q45)
    # Four numbers a body stored, and `F` rebuilt from them where it is read: 9 stored
    # entries of `F` cost more memory traffic than the few products that rebuild them.
    D = rotation_minus_identity(materialise(quaternion, one))
    F = tuple(d + 1 if i % 4 == 0 else d for i, d in enumerate(D))
    # Π_{k+1} = Fᵀ Π_k (as a row, Π_kᵀ F): equal to the sequential rotations to round-off
    # (`momenta[-1]`), and its loops read the 4 stored quaternion components instead of
    # the 10 sines and cosines.
    return times_increment(g, D), matmul3(momenta[0], F), rotations, momenta, F


def rk4_field(g, m, w):
    """`(g ŵ, Π × w)`, component-wise; `g` 9 arrays (or some rows), `w` 3 arrays."""
    dm = (
        m[1] * w[2] - m[2] * w[1],
        m[2] * w[0] - m[0] * w[2],
        m[0] * w[1] - m[1] * w[0],
    )
    # (g ŵ)_{ij} = Σ_k g_ik ŵ_kj, ŵ = [[0, −w2, w1], [w2, 0, −w0], [−w1, w0, 0]].
    dg = []
    for i in range(len(g) // 3):
        g0, g1, g2 = g[3 * i], g[3 * i + 1], g[3 * i + 2]
        dg += [g1 * w[2] - g2 * w[1], g2 * w[0] - g0 * w[2], g0 * w[1] - g1 * w[0]]
    return tuple(dg), dm


def rk4_primal(g, m, rate):
    """`rk4_step`'s arithmetic: `(g_next, Π_next, stages)`, `stages` the four
    `(stage input, increment, w)` triples `((g_i, Π_i), (k_g, k_Π), w_i)`, `w_i = hΩ_i`."""
    y = (tuple(g), tuple(m))
    stages = []
    for c in (None, 0.5, 0.5, 1.0):
        yi = y if c is None else tuple(_axpy(c, k, x) for k, x in zip(stages[-1][1], y))
        w = tuple(yi[1][i] * rate[i] for i in range(3))
        stages.append((yi, rk4_field(*yi, w), w))
    k1, k2, k3, k4 = (k for _, k, _ in stages)

    def combine(y, a, b, c, e):
        return tuple(
            yi + (ai + 2 * bi + 2 * ci + ei) / 6 for yi, ai, bi, ci, ei in zip(y, a, b, c, e)
        )

    g_next = combine(y[0], k1[0], k2[0], k3[0], k4[0])
    m_next = combine(y[1], k1[1], k2[1], k3[1], k4[1])
    return g_next, m_next, stages


def _axpy(a, k, y):
    return tuple(yi + a * ki for yi, ki in zip(y, k))
