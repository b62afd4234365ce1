"""The SE(3) DEP residual `dφ⁻¹(ξ)ᵀ Mξ/h − m` and its Jacobian in closed form, as
structure of arrays (paper (4.8) on SE(3); derivation below).

`residual` is the equation the Newton iteration of `_se3.py` solves and the implicit
function theorem differentiates; `operator` and `e_blocks` are its pieces (the operator
`dφ⁻¹(ξ)ᵀ` applied to a momentum, and the derivative of that at fixed momentum). The
coefficients are power series in `u = θ²/4` (`_soa.py`), accurate to round-off up to
θ = π, with no library trigonometry.

Derivation. For increment `ξ = (ω, v)` and `μ = (a, b) = Mξ/h`, the left-invariant DEP
equation `dφ⁻¹(ξ)ᵀ μ = m` has the block structure of `lievi.SE3`: with
`K = dφ⁻¹_SO(3)(ω)ᵀ` (the SO(3) equation's operator) and `L` its translation block,

    r_ω = K a + L b − Π,      r_v = K′ b − P,

where, with `t = |ω|²`, `s = ω·v`,

- exp chart: `K y = K′ y = y + ω×y/2 + c(t)(ω(ω·y) − t y)`, `c = (1 − (θ/2)cot(θ/2))/θ²`,
  and `L y = v×y/2 + 2c′(t)s(ω(ω·y) − t y) + c(ω(v·y) + v(ω·y) − 2s y)` (the transpose of
  `∂_v J⁻¹`, `lievi.SE3.dexpinv`'s lower-left block, expanded with
  `v×(ω×y) = ω(v·y) − y s`);
- Cayley chart: `K y = y + ω×y/2 + ω(ω·y)/4`, `K′ y = y + ω×y/2`, `L y = v×K′y/2` (the
  transpose of `lievi.SE3.dcayinv`);

and its Jacobian is `dφ⁻¹(ξ)ᵀ M/h + E`, with `E` the derivative of `dφ⁻¹(ξ)ᵀ μ` at fixed
`μ` (`_e_blocks`; needs `c′` and `c″`). The coefficients are power series in `u = θ²/4`,
accurate to round-off up to θ = π (the exp chart's domain), with no library
trigonometry. The tests check `r`, `∂r/∂ξ`, the reduced Jacobian and the step with its
gradients against `jax.jacfwd` of the residual built from `lievi.SE3.dexpinv`/`dcayinv`
and against the generic path.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp

from ._base import materialise, ones
from ._soa import P_SERIES, S_SERIES, dot, flat, horner, inverse3, nested

# (θ − sin θ)/θ³ = Σ (−1)ᵏ tᵏ/(2k + 3)!, t = θ²: 13 terms reach round-off at θ = π.
SINC3 = tuple((-1) ** k / math.factorial(2 * k + 3) for k in range(13))


def _horner2(coefficients, u):
    """`(p(u), p′(u), p″(u))`."""
    value, first, second = (jnp.zeros_like(u) for _ in range(3))
    for c in reversed(coefficients):
        second = second * u + 2 * first
        first = first * u + value
        value = value * u + c
    return value, first, second


def dexpinv_coefficients(t):
    """`(c, c′, c″)` in `t = θ²`, `c = (1 − (θ/2)cot(θ/2))/θ² = P/(4S)` (`_so3`'s
    series in `u = t/4`)."""
    S, S1, S2 = _horner2(S_SERIES, t / 4)
    P, P1, P2 = _horner2(P_SERIES, t / 4)
    N1 = P1 * S - P * S1
    f1 = N1 / (4 * S * S)
    f2 = ((P2 * S - P * S2) * S - 2 * S1 * N1) / (4 * S * S * S)
    return P / (4 * S), f1 / 4, f2 / 16


def mv(X, y):
    return tuple(X[i][0] * y[0] + X[i][1] * y[1] + X[i][2] * y[2] for i in range(3))


def exp_series(t):
    """The exp chart's coefficients in `t = θ²`: `(c, c′, c″)` of `dexpinv`
    (`dexpinv_coefficients`) and `β = (1 − cos θ)/θ²`, `γ = (θ − sin θ)/θ³` of its inverse."""
    c, c1, c2 = dexpinv_coefficients(t)
    S = horner(S_SERIES, t / 4)
    return c, c1, c2, S * S / 2, horner(SINC3, t)


def operator(chart, w, v, coefficients=None):
    """The blocks `(K, L, K′)` of `dφ⁻¹(ξ)ᵀ = [[K, L], [0, K′]]` as 3×3 nested tuples, and
    the exp chart's coefficients `(c, c′, c″)` (`None` for Cayley).

    exp:    K = K′ = (1 − ct) + ω̂/2 + c ωωᵀ,
            L = v̂/2 − (kt + 2cs) + k ωωᵀ + c(ωvᵀ + vωᵀ),  k = 2c′s;
    Cayley: K′ = 1 + ω̂/2,  K = K′ + ωωᵀ/4,  L = v̂/2 + (ωvᵀ − s)/4
    (`t = |ω|²`, `s = ω·v`; the module doc).
    """
    t, s = dot(w, w), dot(w, v)
    if chart == "cayley":
        diag_k, coef_ww, coefficients = 1.0, 0.25, None
        diag_l, coef_l = -s / 4, 0.25
    else:
        coefficients = dexpinv_coefficients(t) if coefficients is None else coefficients
        c, c1, _ = coefficients
        k = 2 * c1 * s
        diag_k, coef_ww = 1 - c * t, c
        diag_l = -(k * t + 2 * c * s)
        coef_l = c
    hw = ((None, -w[2], w[1]), (w[2], None, -w[0]), (-w[1], w[0], None))
    hv = ((None, -v[2], v[1]), (v[2], None, -v[0]), (-v[1], v[0], None))
    Kp, K, L = [], [], []
    for i in range(3):
        kp_row, k_row, l_row = [], [], []
        for j in range(3):
            if i == j:
                kp = diag_k if chart == "exp" else 1.0
                k = diag_k + coef_ww * w[i] * w[i]
                if chart == "exp":
                    l_entry = (
                        diag_l + coefficients[1] * 2 * s * w[i] * w[i] + 2 * coef_l * w[i] * v[i]
                    )
                else:
                    l_entry = diag_l + coef_l * w[i] * v[i]
            else:
                kp = hw[i][j] / 2
                k = kp + coef_ww * w[i] * w[j]
                if chart == "exp":
                    l_entry = (
                        hv[i][j] / 2
                        + coefficients[1] * 2 * s * w[i] * w[j]
                        + coef_l * (w[i] * v[j] + v[i] * w[j])
                    )
                else:
                    l_entry = hv[i][j] / 2 + coef_l * w[i] * v[j]
            kp_row.append(kp)
            k_row.append(k)
            l_row.append(l_entry)
        Kp.append(tuple(kp_row))
        K.append(tuple(k_row))
        L.append(tuple(l_row))
    K, L = tuple(K), tuple(L)
    Kp = K if chart == "exp" else tuple(Kp)
    return K, L, Kp, coefficients


def residual(chart, x, m, A, with_jacobian: bool):
    """`r = dφ⁻¹(x)ᵀ A x − m` and, if asked, `∂r/∂x = dφ⁻¹(x)ᵀ A + E` (the module doc).

    `x`, `m`: 6-tuples of arrays; `A = M/h`: 6×6 nested tuple. Returns `(r, J)`, `J` a 6×6
    nested tuple (or `None`).
    """
    w, v = x[:3], x[3:]
    mu = tuple(sum(A[i][j] * x[j] for j in range(6)) for i in range(6))
    a, b = mu[:3], mu[3:]
    K, L, Kp, coefficients = operator(chart, w, v)
    if with_jacobian:
        # Every entry of J reads K, L, K′: stored once instead of recomputed in each
        # consumer (`materialise`).
        flat = materialise(
            [e for X in (K, L) + ((Kp,) if chart == "cayley" else ()) for row in X for e in row],
            ones(x[0]),
        )
        K = tuple(tuple(flat[3 * i : 3 * i + 3]) for i in range(3))
        L = tuple(tuple(flat[9 + 3 * i : 12 + 3 * i]) for i in range(3))
        Kp = K if chart == "exp" else tuple(tuple(flat[18 + 3 * i : 21 + 3 * i]) for i in range(3))
    Ka, Lb, Kpb = mv(K, a), mv(L, b), mv(Kp, b)
    r = tuple(Ka[i] + Lb[i] - m[i] for i in range(3)) + tuple(Kpb[i] - m[3 + i] for i in range(3))
    if not with_jacobian:
        return r, None

    E_ww, E_wv, E_vw = e_blocks(chart, w, v, a, b, Kpb, coefficients)
    J = []
    for i in range(3):
        J.append(
            tuple(
                sum(K[i][k] * A[k][j] + L[i][k] * A[3 + k][j] for k in range(3))
                + (E_ww[i][j] if j < 3 else E_wv[i][j - 3])
                for j in range(6)
            )
        )
    for i in range(3):
        J.append(
            tuple(
                sum(Kp[i][k] * A[3 + k][j] for k in range(3)) + (E_vw[i][j] if j < 3 else 0)
                for j in range(6)
            )
        )
    return r, tuple(J)


def e_blocks(chart, w, v, a, b, Kpb, coefficients):
    """`(E_ωω, E_ωv, E_vω)`: the blocks of `E = ∂(dφ⁻¹(ξ)ᵀμ)/∂ξ` at fixed `μ = (a, b)`
    (`E_vv = 0`), `Kpb = K′b`."""
    oa, ob, vb = dot(w, a), dot(w, b), dot(v, b)
    t, s = dot(w, w), dot(w, v)
    if chart == "cayley":
        # E_ωω = −â/2 + (ω·a + v·b)/4 + (ωaᵀ − bvᵀ)/4, E_ωv = −(K′b)^/2, E_vω = −b̂/2.
        d = (oa + vb) / 4
        E_ww = tuple(
            tuple((d if i == j else 0) + (w[i] * a[j] - b[i] * v[j]) / 4 for j in range(3))
            for i in range(3)
        )
        E_ww = add_hat(E_ww, a, -0.5)
        E_wv = add_hat(((0,) * 3,) * 3, Kpb, -0.5)
        E_vw = add_hat(((0,) * 3,) * 3, b, -0.5)
    else:
        c, c1, c2 = coefficients
        k = 2 * c1 * s
        za = tuple(w[i] * oa - t * a[i] for i in range(3))
        zb = tuple(w[i] * ob - t * b[i] for i in range(3))
        lw = tuple(w[i] * vb + v[i] * ob - 2 * s * b[i] for i in range(3))
        y = tuple(2 * c1 * zb[i] - 2 * c * b[i] for i in range(3))
        u = tuple(
            -2 * c * a[i] + 2 * c1 * (za[i] + lw[i]) + 4 * s * (c2 * zb[i] - c1 * b[i])
            for i in range(3)
        )
        d_ww = c * (oa + vb) + k * ob
        d_b = c * ob
        ca_kb = tuple(c * a[j] + k * b[j] for j in range(3))
        cb = tuple(c * b[j] for j in range(3))
        E_ww = tuple(
            tuple(
                (d_ww if i == j else 0) + w[i] * ca_kb[j] + v[i] * cb[j] + u[i] * w[j] + y[i] * v[j]
                for j in range(3)
            )
            for i in range(3)
        )
        E_ww = add_hat(E_ww, a, -0.5)
        D_b = tuple(
            tuple((d_b if i == j else 0) + w[i] * cb[j] + y[i] * w[j] for j in range(3))
            for i in range(3)
        )
        E_wv = E_vw = add_hat(D_b, b, -0.5)
    return E_ww, E_wv, E_vw


def add_hat(X, y, alpha):
    """`X + α ŷ` (3×3 nested tuples), without adding the zero diagonal of `ŷ`."""
    H = ((None, -y[2], y[1]), (y[2], None, -y[0]), (-y[1], y[0], None))
    return tuple(
        tuple(X[i][j] if H[i][j] is None else X[i][j] + alpha * H[i][j] for j in range(3))
        for i in range(3)
    )


def factor(J):
    """What `solve6` needs of `J = [[P, Q], [R, S]]`: `(P⁻¹, P⁻¹Q, R, (S − R P⁻¹Q)⁻¹)`,
    block elimination with 3×3 Cramer inverses, materialised (each is read by several
    consumers)."""
    one = ones(J[0][0])
    P = tuple(J[i][:3] for i in range(3))
    Q = tuple(J[i][3:] for i in range(3))
    R = tuple(J[3 + i][:3] for i in range(3))
    S = tuple(J[3 + i][3:] for i in range(3))
    Pinv = nested(materialise(flat(inverse3(P)), one))
    PinvQ = tuple(
        tuple(sum(Pinv[i][k] * Q[k][j] for k in range(3)) for j in range(3)) for i in range(3)
    )
    PinvQ = nested(materialise(flat(PinvQ), one))
    schur = tuple(
        tuple(S[i][j] - sum(R[i][k] * PinvQ[k][j] for k in range(3)) for j in range(3))
        for i in range(3)
    )
    schur_inv = nested(materialise(flat(inverse3(schur)), one))
    return Pinv, PinvQ, R, schur_inv


def solve6(factors, r):
    """`J⁻¹ r` from `factor(J)`: `x₂ = (S − R P⁻¹Q)⁻¹(r₂ − R P⁻¹r₁)`, `x₁ = P⁻¹r₁ − P⁻¹Q x₂`."""
    Pinv, PinvQ, R, schur_inv = factors
    y1 = mv(Pinv, r[:3])
    Ry1 = mv(R, y1)
    x2 = mv(schur_inv, tuple(r[3 + i] - Ry1[i] for i in range(3)))
    Qx2 = mv(PinvQ, x2)
    return tuple(y1[i] - Qx2[i] for i in range(3)) + x2


class SE3Equation(eqx.Module):
    """The SE(3) DEP equation in the chart `chart`, as `_implicit.differentiable_root`
    reads it: `residual` and the block solve `solve6`."""

    chart: object = eqx.field(static=True)

    def residual(self, x, m, A, with_jacobian: bool):
        return residual(self.chart, x, m, A, with_jacobian)

    def solve(self, J, r):
        return solve6(factor(J), r)
