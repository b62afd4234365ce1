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

from .._results import RESULTS
from . import _explicit_adjoints
from ._kernel import AbstractBatchKernel, materialise


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


def _sin_quarter_turns(r, u, q):
    """`sin(r + qπ/2)` for `|r| ≤ π/4`, `u = r²`, `q` integer: `±sin r` for even `q`,
    `±cos r` for odd. One polynomial a value: its coefficients are those of `sin r / r`
    or of `cos r` by the parity of `q` (a select a coefficient, not both polynomials and a
    select of the results)."""
    # Integer bit operations (two's complement: `q & 3` is q mod 4 for negative q too): a
    # float `mod` is a scalar `fmod` call on CPU.
    odd = (q & 1) == 1
    value = jnp.where(odd, _COS[-1], _SIN[-1])
    for s, c in zip(reversed(_SIN[:-1]), reversed(_COS[:-1])):
        value = value * u + jnp.where(odd, c, s)
    value = jnp.where(odd, value, r * value)
    return jnp.where((q & 2) == 2, -value, value)


def sincos(x):
    """`(sin x, cos x)` elementwise, by range reduction and polynomials (no libm calls)."""
    k = jnp.round(x * (2 / math.pi))
    r = ((x - k * _P1) - k * _P2) - k * _P3
    # x = r + kπ/2, and cos x = sin(r + (k + 1)π/2).
    q = k.astype(jnp.int32)
    return _sin_quarter_turns(r, r * r, q), _sin_quarter_turns(r, r * r, q + 1)


def _finite_result(Pi, g):
    finite = jnp.isfinite(Pi[0])
    for x in (*Pi[1:], *g):
        finite = finite & jnp.isfinite(x)
    return jnp.where(finite, RESULTS.successful, RESULTS.nonfinite).astype(jnp.int32)


def _times_axis_quaternion(quaternion, p: int, c, s):
    """`q ⊗ (c, s e_p)` for `q = (w, x, y, z)` (4 arrays, or Python zeros): the rotation
    `R(q) exp(α ê_p)` for `(c, s) = (cos α/2, sin α/2)`; 8 products, 4 sums."""
    w, v = quaternion[0], quaternion[1:]
    q, r = (p + 1) % 3, (p + 2) % 3
    out = [None] * 3
    out[p] = w * s + c * v[p]
    out[q] = c * v[q] + s * v[r]
    out[r] = c * v[r] - s * v[q]
    return (w * c - s * v[p], *out)


def _rotation_of_quaternion(quaternion):
    """`R(q)` for a unit quaternion `q = (w, x, y, z)`: 9 arrays, row-major."""
    w, x, y, z = quaternion
    return (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )


def _matmul3(X, Y):
    """`X Y` for 3×3 matrices as 9 arrays; `X` may also be fewer rows (3 arrays a row),
    e.g. the advected row `Γᵀ`."""
    return tuple(
        X[3 * i] * Y[j] + X[3 * i + 1] * Y[3 + j] + X[3 * i + 2] * Y[6 + j]
        for i in range(len(X) // 3)
        for j in range(3)
    )


# (axis, fraction of h) of the palindromic splitting's sub-flows, as `_splitting.py`.
SUBFLOWS = ((0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5))


def splitting_primal(g, Pi, rate):
    """`splitting_step`'s arithmetic: `(g_next, Π_next, [(cos α_j, sin α_j)], [Π^{(j)}], F)`,
    the rotations, the momenta before and after each sub-flow (`j = 0…5`) and the
    composed increment `F = F_1⋯F_5` (9 arrays)."""
    one = Pi[0] * 0 + 1
    quaternion = None
    rotations, momenta = [], [tuple(Pi)]
    for p, fraction in SUBFLOWS:
        # The half angle α/2 = (f/2)·Π_p·(h/I_p): a product. As a quotient by I_p/h it
        # was a division a sub-flow, which XLA evaluates once and stores (see
        # `materialise`): one more array written and read back per angle.
        sin_half, cos_half = materialise(sincos((0.5 * fraction) * Pi[p] * rate[p]), one)
        c, s = 1 - 2 * sin_half * sin_half, 2 * sin_half * cos_half
        q, r = (p + 1) % 3, (p + 2) % 3
        Pi = list(Pi)
        Pi[q], Pi[r] = c * Pi[q] + s * Pi[r], c * Pi[r] - s * Pi[q]
        rotations.append((c, s))
        momenta.append(tuple(Pi))
        if quaternion is None:
            quaternion = (cos_half, *(sin_half if i == p else 0.0 for i in range(3)))
        else:
            quaternion = _times_axis_quaternion(quaternion, p, cos_half, sin_half)
    # Four numbers a body stored, and `F` rebuilt from them where `g F` reads it: 9 stored
    # entries of `F` cost more memory traffic than the few products that rebuild them.
    F = _rotation_of_quaternion(materialise(quaternion, one))
    return _matmul3(g, F), tuple(Pi), rotations, momenta, F


def splitting_step(g, Pi, rate):
    """One `LiePoissonSplitting` step: axes 0, 1 (h/2), 2 (h), 1, 0 (h/2), as `_splitting.py`.

    Sub-flow about axis `p` for a fraction `f` of the step: `F_j = exp(α ê_p)` with
    `α = f Π_p h/I_p`, `Π ← F_jᵀ Π` (`Π_p` does not change). The five rotations are
    composed as unit quaternions `(cos α/2, sin α/2 e_p)` into `F = F_1⋯F_5`, and
    `g ← g F` once (equal to rotating `g` five times, to round-off). `g`: 9 arrays
    (row-major), or only some of its rows (as `dep_step`), `Pi`: 3 arrays, `rate`: `h/I_p`,
    3 arrays or scalars. Returns `(g_next, Pi_next, result)`. Differentiable by the
    hand-written tangent of `_explicit_adjoints.splitting_flow`.

    Cost (XLA on CPU, float64): the step is bound by the arrays of `B` numbers it writes
    and reads back, more than by its arithmetic. Per body-step the five sine/cosine
    pairs of the half angles (10 numbers, each from one polynomial) and the four
    quaternion components are stored; the momenta between sub-flows and `F` are
    recomputed where they are read. Storing the 9 entries of `F` instead of the
    quaternion, and each angle (a division by `I/h`), was measured 1.2–1.4× slower at
    batch 1e5 (same run).
    """
    g, Pi = _explicit_adjoints.splitting_flow(tuple(g), tuple(Pi), tuple(rate))
    return g, Pi, _finite_result(Pi, g)


def rk4_field(g, Pi, w):
    """`(g ŵ, Π × w)`, component-wise; `g` 9 arrays (or some rows), `w` 3 arrays."""
    dPi = (
        Pi[1] * w[2] - Pi[2] * w[1],
        Pi[2] * w[0] - Pi[0] * w[2],
        Pi[0] * w[1] - Pi[1] * w[0],
    )
    # (g ŵ)_{ij} = Σ_k g_ik ŵ_kj, ŵ = [[0, −w2, w1], [w2, 0, −w0], [−w1, w0, 0]].
    dg = []
    for i in range(len(g) // 3):
        g0, g1, g2 = g[3 * i], g[3 * i + 1], g[3 * i + 2]
        dg += [g1 * w[2] - g2 * w[1], g2 * w[0] - g0 * w[2], g0 * w[1] - g1 * w[0]]
    return tuple(dg), dPi


def rk4_primal(g, Pi, rate):
    """`rk4_step`'s arithmetic: `(g_next, Π_next, stages)`, `stages` the four
    `(stage input, increment, w)` triples `((g_i, Π_i), (k_g, k_Π), w_i)`, `w_i = hΩ_i`."""
    y = (tuple(g), tuple(Pi))
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
    Pi_next = combine(y[1], k1[1], k2[1], k3[1], k4[1])
    return g_next, Pi_next, stages


def _axpy(a, k, y):
    return tuple(yi + a * ki for yi, ki in zip(y, k))


def rk4_step(g, Pi, rate):
    """One `RK4` step on `ṁ = Π × Ω`, `ġ = g Ω̂`, `Ω = I⁻¹Π` (`_rk4.py`), component-wise.

    `rate`: `h/I_p`, 3 arrays or scalars. The step and the moments enter only through
    these ratios (`h f(y; I) = f(y; I/h)`, the field is linear in `I⁻¹`): the stages use
    the increments `h k_i = (g ŵ_i, Π_i × w_i)`, `w_i = (h/I)·Π_i`, so reverse mode
    carries three cotangents of the parameters, not four. Differentiable by the
    hand-written tangent of `_explicit_adjoints.rk4_flow`.
    """
    g_next, Pi_next = _explicit_adjoints.rk4_flow(tuple(g), tuple(Pi), tuple(rate))
    return g_next, Pi_next, _finite_result(Pi_next, g_next)


def _explicit_info(Pi):
    # Explicit: no Newton iterations, zero residual (as the per-body `StepInfo`).
    return jnp.zeros(jnp.shape(Pi[0]), jnp.int32), jnp.zeros(jnp.shape(Pi[0]), Pi[0].dtype)


class SplittingKernel(AbstractBatchKernel):
    """`splitting_step` for `LiePoissonSplitting`."""

    def prepare(self, inertia, h):
        return tuple(h / moment for moment in inertia)

    def step(self, params, g, Pi, alive):
        g_next, Pi_next, result = splitting_step(g, Pi, params)
        return (g_next, Pi_next, result, *_explicit_info(Pi))


class RK4Kernel(AbstractBatchKernel):
    """`rk4_step` for `RK4`."""

    def prepare(self, inertia, h):
        return tuple(h / moment for moment in inertia)

    def step(self, params, g, Pi, alive):
        g_next, Pi_next, result = rk4_step(g, Pi, params)
        return (g_next, Pi_next, result, *_explicit_info(Pi))
