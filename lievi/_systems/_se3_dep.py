"""The DEP equation of a rigid body on SE(3) in closed form (paper (4.8); `lievi.DEP`).

For `RigidBodySE3` with kinetic tensor `M`, increment `ξ = (ω, v)` and `μ = (a, b) = Mξ/h`,
the left-invariant DEP equation `dφ⁻¹(ξ)ᵀ μ = m` has the block structure of `lievi.SE3`:
with `K = dφ⁻¹_SO(3)(ω)ᵀ` (the SO(3) equation's operator) and `L` its translation block,

    r_ω = K a + L b − Π,      r_v = K' b − P,

where, with `t = |ω|²`, `s = ω·v`,

- exp chart: `K y = K' y = y + ω×y/2 + c(t)(ω(ω·y) − t y)`, `c = (1 − (θ/2)cot(θ/2))/θ²`,
  and `L y = v×y/2 + 2c′(t)s(ω(ω·y) − t y) + c(ω(v·y) + v(ω·y) − 2s y)` (the transpose of
  `∂_v J⁻¹`, `lievi.SE3.dexpinv`'s lower-left block, expanded with `v×(ω×y) = ω(v·y) − y s`);
- Cayley chart: `K y = y + ω×y/2 + ω(ω·y)/4`, `K' y = y + ω×y/2`, `L y = v×K' y/2`
  (the transpose of `lievi.SE3.dcayinv`).

and its Jacobian is `dφ⁻¹(ξ)ᵀ M/h + E`, with `E` the derivative of `dφ⁻¹(ξ)ᵀ μ` at fixed `μ`
(written out in `_blocks`; needs `c′` and `c″`). `RigidBodySE3.kernel_step` runs the whole
DEP step from here: Newton with this Jacobian, the 6×6 system solved by blocks with 3×3
Cramer inverses, then `F = φ(ξ)`, `Ad_Fᵀ m` (DLP 3.3) and `g F` (2.9). It takes the same
Newton iterates as the generic path (`jax.jacfwd` of the residual built from
`lievi.SE3.dexpinv`/`dcayinv`, `linalg.solve`), at a fraction of the cost
(`benchmarks/se3_step_cost.py`).

As in the SO(3) fast step (`lievi._batch._fast_so3`) everything is written on scalars, so
that XLA emits elementwise loops (long ones under `vmap`), and without library
trigonometry: the coefficients are power series in `u = θ²/4`, accurate to round-off up to
θ = π (the exp chart's domain). Derivatives of the root come from the implicit function
theorem (`_at_root`), not from the Newton iterations. The tests check `r`, `∂r/∂ξ`, the
step and its gradients against the generic path.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from .._batch._fast_so3 import _C, _P, _S, _cross, _dot
from .._results import RESULTS


def _horner2(coefficients, u):
    """`(p(u), p′(u), p″(u))` of the polynomial with these coefficients."""
    value, first, second = (jnp.zeros_like(u) for _ in range(3))
    for c in reversed(coefficients):
        second = second * u + 2 * first
        first = first * u + value
        value = value * u + c
    return value, first, second


def _dexpinv_coefficient(t):
    """`(c, c′, c″)` in `t = θ²` for `c = (1 − (θ/2)cot(θ/2))/θ²` `= f(u) = P/(4S)`, `u = t/4`."""
    S, S1, S2 = _horner2(_S, t / 4)
    P, P1, P2 = _horner2(_P, t / 4)
    N1 = P1 * S - P * S1  # f′ = N1/(4S²)
    f1 = N1 / (4 * S * S)
    f2 = ((P2 * S - P * S2) * S - 2 * S1 * N1) / (4 * S * S * S)
    return P / (4 * S), f1 / 4, f2 / 16


# 3×3 matrices as nested tuples of scalars (structure of arrays).
def _hat(x):
    z = jnp.zeros_like(x[0])
    return ((z, -x[2], x[1]), (x[2], z, -x[0]), (-x[1], x[0], z))


def _lin(*terms):
    """`Σ αₖ Xₖ` for pairs `(α, X)`; `X = None` stands for the identity."""
    out = [[0.0] * 3 for _ in range(3)]
    for alpha, X in terms:
        for i in range(3):
            for j in range(3):
                entry = (alpha if i == j else 0.0) if X is None else alpha * X[i][j]
                out[i][j] = out[i][j] + entry
    return tuple(tuple(row) for row in out)


def _mm(X, Y):
    return tuple(
        tuple(sum(X[i][k] * Y[k][j] for k in range(3)) for j in range(3)) for i in range(3)
    )


def _mv(X, y):
    return tuple(sum(X[i][k] * y[k] for k in range(3)) for i in range(3))


def _point(chart, x, A):
    """What the residual and its Jacobian share at `x`: `(ω, v, a, b, t, s, c, c′, c″)`
    with `(a, b) = A x`, `t = |ω|²`, `s = ω·v` and the exp chart's coefficients (zeros
    for Cayley). Computed once per Newton iterate and carried to the next iteration's
    Jacobian, so each iteration evaluates them once."""
    omega, v = x[:3], x[3:]
    mu = tuple(sum(A[i][j] * x[j] for j in range(6)) for i in range(6))
    t, s = _dot(omega, omega), _dot(omega, v)
    if chart == "exp":
        c, c1, c2 = _dexpinv_coefficient(t)
    else:
        c = c1 = c2 = jnp.zeros_like(t)
    return _barrier((omega, v, mu[:3], mu[3:], t, s, c, c1, c2))


def _z(omega, t, y):
    """`ω(ω·y) − t y` `= ω̂²y`."""
    oy = _dot(omega, y)
    return tuple(omega[i] * oy - t * y[i] for i in range(3))


def _residual_at(chart, point, m):
    """`r = dφ⁻¹(ξ)ᵀ μ − m` from `_point`, with the operators applied as vectors."""
    omega, v, a, b, t, s, c, c1, _ = point
    oa, ob = _dot(omega, a), _dot(omega, b)
    wa, wb = _cross(omega, a), _cross(omega, b)
    if chart == "cayley":
        Ka = tuple(a[i] + wa[i] / 2 + omega[i] * oa / 4 for i in range(3))
        Kb = tuple(b[i] + wb[i] / 2 for i in range(3))  # K′b
        Lb = tuple(y / 2 for y in _cross(v, Kb))
    else:
        za, zb = _z(omega, t, a), _z(omega, t, b)
        Ka = tuple(a[i] + wa[i] / 2 + c * za[i] for i in range(3))
        Kb = tuple(b[i] + wb[i] / 2 + c * zb[i] for i in range(3))
        vb, vxb = _dot(v, b), _cross(v, b)
        Lb = tuple(
            vxb[i] / 2 + 2 * c1 * s * zb[i] + c * (omega[i] * vb + v[i] * ob - 2 * s * b[i])
            for i in range(3)
        )
    return tuple(Ka[i] + Lb[i] - m[i] for i in range(3)) + tuple(Kb[i] - m[3 + i] for i in range(3))


def _rank1(*terms):
    """`Σ αₖ I + Σ xₖ yₖᵀ − ½ Σ ŷₖ` for terms `("I", α)`, `("outer", x, y)`, `("hat", y)`."""
    out = [[0.0] * 3 for _ in range(3)]
    for term in terms:
        kind = term[0]
        for i in range(3):
            for j in range(3):
                if kind == "I" and i == j:
                    out[i][j] = out[i][j] + term[1]
                elif kind == "outer":
                    out[i][j] = out[i][j] + term[1][i] * term[2][j]
                elif kind == "hat" and i != j:
                    y = term[1]
                    # −½ ŷ: ŷ[i][j] = −ε_ijk y_k.
                    k = 3 - i - j
                    sign = 1.0 if (i, j) in ((0, 1), (1, 2), (2, 0)) else -1.0
                    out[i][j] = out[i][j] + sign * y[k] / 2
    return tuple(tuple(row) for row in out)


def _jacobian_at(chart, point, A):
    """`∂r/∂ξ = dφ⁻¹(ξ)ᵀ A + E` from `_point` (blocks and `E` derived in the module
    docstring), as a 6×6 nested tuple."""
    omega, v, a, b, t, s, c, c1, c2 = point
    oa, ob, vb = _dot(omega, a), _dot(omega, b), _dot(v, b)
    half_w = tuple(y / 2 for y in omega)
    if chart == "cayley":
        # K = 1 + ω̂/2 + ωωᵀ/4, K′ = 1 + ω̂/2, L = v̂K′/2 = v̂/2 + (ωvᵀ − s)/4.
        q4 = tuple(y / 4 for y in omega)
        Kp = _rank1(("I", 1.0), ("hat", tuple(-y for y in omega)))
        K = _rank1(("I", 1.0), ("hat", tuple(-y for y in omega)), ("outer", q4, omega))
        L = _rank1(("I", -s / 4), ("hat", tuple(-y for y in v)), ("outer", q4, v))
        Kb = tuple(b[i] + _cross(half_w, b)[i] for i in range(3))
        E_ww = _rank1(
            ("hat", a),
            ("I", (oa + vb) / 4),
            ("outer", q4, a),
            ("outer", tuple(-y / 4 for y in b), v),
        )
        E_wv, E_vw = _rank1(("hat", Kb)), _rank1(("hat", b))
    else:
        # K = K′ = (1 − ct) + ω̂/2 + c ωωᵀ, L = v̂/2 + 2c′s(ωωᵀ − t) + c(ωvᵀ + vωᵀ − 2s).
        cw = tuple(c * y for y in omega)
        K = _rank1(("I", 1 - c * t), ("hat", tuple(-y for y in omega)), ("outer", cw, omega))
        k = 2 * c1 * s
        kw = tuple(k * y for y in omega)
        L = _rank1(
            ("I", -k * t - 2 * c * s),
            ("hat", tuple(-y for y in v)),
            ("outer", kw, omega),
            ("outer", cw, v),
            ("outer", tuple(c * y for y in v), omega),
        )
        Kp = K
        za, zb = _z(omega, t, a), _z(omega, t, b)
        w = tuple(omega[i] * vb + v[i] * ob - 2 * s * b[i] for i in range(3))
        # E_ωω = ∂_ω(K a) + ∂_ω(L b) and ∂_v(L b) = ∂_ω(K b) (the same matrix), grouped
        # by the right factor of each rank-one term.
        y = tuple(2 * c1 * zb[i] - 2 * c * b[i] for i in range(3))
        u = tuple(
            -2 * c * a[i] + 2 * c1 * (za[i] + w[i]) + 4 * s * (c2 * zb[i] - c1 * b[i])
            for i in range(3)
        )
        cb = tuple(c * y_ for y_ in b)
        E_ww = _rank1(
            ("hat", a),
            ("I", c * (oa + vb) + k * ob),
            ("outer", omega, tuple(c * a[i] + k * b[i] for i in range(3))),
            ("outer", v, cb),
            ("outer", u, omega),
            ("outer", y, v),
        )
        E_wv = E_vw = _rank1(("hat", b), ("I", c * ob), ("outer", omega, cb), ("outer", y, omega))
    K, L, Kp, E_ww, E_wv, E_vw = _barrier((K, L, Kp, E_ww, E_wv, E_vw))

    def times_rows(X, r0):  # X · A[r0:r0+3, :]
        return tuple(
            tuple(sum(X[i][k] * A[r0 + k][j] for k in range(3)) for j in range(6)) for i in range(3)
        )

    KA, LA, KpA = times_rows(K, 0), times_rows(L, 3), times_rows(Kp, 3)
    top = tuple(
        tuple(KA[i][j] + LA[i][j] + (E_ww[i][j] if j < 3 else E_wv[i][j - 3]) for j in range(6))
        for i in range(3)
    )
    bottom = tuple(
        tuple(KpA[i][j] + E_vw[i][j] if j < 3 else KpA[i][j] for j in range(6)) for i in range(3)
    )
    return top + bottom


def residual(chart: str, x, m, A, with_jacobian: bool):
    """`r = dφ⁻¹(x)ᵀ A x − m` and, if asked, `∂r/∂x = dφ⁻¹(x)ᵀ A + E` (`_jacobian_at`).

    All arguments structure of arrays: `x`, `m` 6-tuples, `A = M/h` a 6×6 nested tuple.
    Returns `(r, J)` as a 6-tuple and a 6×6 nested tuple (`J = None` without the Jacobian).
    """
    point = _point(chart, x, A)
    r = _residual_at(chart, point, m)
    return r, (_jacobian_at(chart, point, A) if with_jacobian else None)


def _barrier(values):
    """The scalars of `values` (a pytree), computed once.

    XLA on CPU fuses a shared scalar subexpression into every consumer, so without this
    each of the six components of a Newton update recomputes the whole Jacobian (~6× the
    work; `lax.optimization_barrier` does not stop it). A reduction is not duplicated: the
    values pass through a sum with zeros, which leaves them unchanged.
    """
    leaves, tree = jax.tree.flatten(values)
    stacked = jnp.stack(jnp.broadcast_arrays(*leaves))
    stacked = jnp.sum(jnp.stack([stacked, jnp.zeros_like(stacked)]), axis=0)
    return jax.tree.unflatten(tree, [stacked[i] for i in range(len(leaves))])


def _inverse3(M):
    (a, b, c), (d, e, f), (g, h, i) = M
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    D, E, F = c * h - b * i, a * i - c * g, b * g - a * h
    G, H, I = b * f - c * e, c * d - a * f, a * e - b * d
    inv = 1 / (a * A + b * B + c * C)
    return ((A * inv, D * inv, G * inv), (B * inv, E * inv, H * inv), (C * inv, F * inv, I * inv))


def solve6(J, r):
    """`J⁻¹ r` for a 6×6 `J = [[P, Q], [R, S]]` by block elimination with 3×3 inverses
    (Cramer): `x₂ = (S − R P⁻¹ Q)⁻¹ (r₂ − R P⁻¹ r₁)`, `x₁ = P⁻¹ (r₁ − Q x₂)`. Needs `P`
    invertible: for the DEP equation `J` is `M/h` (positive definite) plus `O(|ξ|)`."""
    P = tuple(J[i][:3] for i in range(3))
    Q = tuple(J[i][3:] for i in range(3))
    R = tuple(J[3 + i][:3] for i in range(3))
    S = tuple(J[3 + i][3:] for i in range(3))
    Pinv = _barrier(_inverse3(P))
    # Separate barriers: under the implicit derivative `r` is a tangent and `J` is not,
    # and one stacked array mixing them would be linear in both.
    PinvQ, Pinv_r1 = _barrier(_mm(Pinv, Q)), _barrier(_mv(Pinv, r[:3]))
    schur = _lin((1.0, S), (-1.0, _mm(R, PinvQ)))
    R_Pinv_r1 = _mv(R, Pinv_r1)
    x2 = _barrier(_mv(_inverse3(schur), tuple(r[3 + i] - R_Pinv_r1[i] for i in range(3))))
    Qx2 = _mv(PinvQ, x2)
    return tuple(Pinv_r1[i] - Qx2[i] for i in range(3)) + x2


def _max_abs(x):
    out = jnp.abs(x[0])
    for y in x[1:]:
        out = jnp.maximum(out, jnp.abs(y))
    return out


# Newton iterations taken unrolled before the loop (each a no-op for a body already
# converged): from the explicit-Euler guess, O(h²) off the root, two reach the tolerance
# for most steps, and the `while_loop` (whose per-iteration overhead is comparable to an
# iteration's arithmetic for one body on CPU) runs only for the rest.
UNROLLED_ITERATIONS = 2


def _newton(chart, guess, m, A, tolerance, max_steps: int):
    """Newton from `guess` until `‖r‖_∞ ≤ tolerance` (or non-finite, or `max_steps`):
    `(x, ‖r‖_∞, iterations)`. Not differentiated (see `_at_root`).

    The first `UNROLLED_ITERATIONS` are unrolled, each applied only where the loop below
    would still iterate, so the iterates and the iteration count are those of the plain
    loop; then a `while_loop` under `lax.cond`, entered only if still needed. The residual
    and the quantities of its Jacobian (`_point`) at each iterate are computed once and
    carried to the next iteration.
    """

    def active(carry):
        _, _, _, norm, it = carry
        return (norm > tolerance) & jnp.isfinite(norm) & (it < max_steps)

    def body(carry):
        x, point, r, _, it = carry
        delta = solve6(_barrier(_jacobian_at(chart, point, A)), r)
        x = _barrier(tuple(x[i] - delta[i] for i in range(6)))
        point = _point(chart, x, A)
        r = _barrier(_residual_at(chart, point, m))
        return x, point, r, _max_abs(r), it + 1

    point = _point(chart, guess, A)
    r = _barrier(_residual_at(chart, point, m))
    carry = (guess, point, r, _max_abs(r), jnp.zeros((), jnp.int32))
    for _ in range(min(UNROLLED_ITERATIONS, max_steps)):
        on = active(carry)
        carry = jax.tree.map(functools.partial(jnp.where, on), body(carry), carry)
    if max_steps > UNROLLED_ITERATIONS:
        carry = jax.lax.cond(
            active(carry), lambda c: jax.lax.while_loop(active, body, c), lambda c: c, carry
        )
    x, _, _, norm, it = carry
    return x, norm, it


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _at_root(chart, x, m, A):
    """`x`, a root of `r(·; m, A)`, with the derivative of the root as a function of `(m, A)`."""
    return x


@_at_root.defjvp
def _at_root_jvp(chart, primals, tangents):
    # Implicit function theorem: J dx = −(∂r/∂m dm + ∂r/∂A dA), with the closed-form J.
    x, m, A = primals
    _, dm, dA = tangents
    _, dr = jax.jvp(lambda mm, AA: residual(chart, x, mm, AA, False)[0], (m, A), (dm, dA))
    _, J = residual(chart, x, m, A, True)
    delta = solve6(J, dr)
    return x, tuple(-d for d in delta)


# (θ − sin θ)/θ³ = Σ (−1)ᵏ tᵏ/(2k + 3)!, t = θ²: 13 terms reach round-off at θ = π.
_SINC3 = tuple((-1) ** k / math.factorial(2 * k + 3) for k in range(13))


def _horner(coefficients, u):
    value = jnp.zeros_like(u)
    for c in reversed(coefficients):
        value = value * u + c
    return value


def dep_step(chart: str, g, m, A, guess, tolerance, max_steps: int):
    """One DEP/DLP step of a left-invariant `RigidBodySE3` (no potential), structure of arrays.

    `g`: the `(4, 4)` pose; `m`: `(6,)`; `A = M/h`: `(6, 6)`; `guess`: the Newton start
    `(6,)` (`h·M⁻¹m`, as `DEP.solve_increment`). Solves the DEP equation, then
    `F = φ(ξ)`, `m_{k+1} = Ad_Fᵀ m` (DLP 3.3) and `g_{k+1} = g F` (2.9) with the rotation
    block re-orthonormalised as `lievi.SE3.compose` does.
    Returns `(g_next, m_next, result, iterations, residual)`; differentiable in `m`, `A`, `g`.
    """
    m_t = tuple(m[i] for i in range(6))
    A_t = tuple(tuple(A[i, j] for j in range(6)) for i in range(6))
    stopped = jax.lax.stop_gradient((m_t, A_t, tolerance))
    x, norm, iterations = _newton(chart, tuple(guess[i] for i in range(6)), *stopped, max_steps)
    finite = norm == norm  # not NaN
    for y in x:
        finite = finite & jnp.isfinite(y)
    # A diverged solve continues from the finite guess (a masked failed step then
    # contributes 0, not NaN, to a gradient), as `newton_solve` does.
    x = tuple(jnp.where(finite, y, jax.lax.stop_gradient(guess[i])) for i, y in enumerate(x))
    x = _at_root(chart, jax.lax.stop_gradient(x), m_t, A_t)

    omega, v = x[:3], x[3:]
    t = _dot(omega, omega)
    W = _hat(omega)
    W2 = _mm(W, W)
    if chart == "exp":
        S, C = _barrier((_horner(_S, t / 4), _horner(_C, t / 4)))
        a, b = S * C, S * S / 2  # sin θ/θ, (1 − cos θ)/θ²
        RF = _lin((1.0, None), (a, W), (b, W2))
        tF = _mv(_lin((1.0, None), (b, W), (_horner(_SINC3, t), W2)), v)
    else:
        alpha = 4 / (4 + t)
        RF = _lin((1.0, None), (alpha, W), (alpha / 2, W2))
        tF = _mv(_lin((0.5, None), (0.5, RF)), v)  # (I + cay Ω)/2 v = (I − Ω/2)⁻¹ v
    RFt = tuple(tuple(RF[j][i] for j in range(3)) for i in range(3))
    Pi, P = m_t[:3], m_t[3:]
    Pxt = (P[1] * tF[2] - P[2] * tF[1], P[2] * tF[0] - P[0] * tF[2], P[0] * tF[1] - P[1] * tF[0])
    m_next = _mv(RFt, tuple(Pi[i] + Pxt[i] for i in range(3))) + _mv(RFt, P)

    R = tuple(tuple(g[i, j] for j in range(3)) for i in range(3))
    p = tuple(g[i, 3] for i in range(3))
    Rn = _mm(R, RF)
    defect = _lin(
        (1.0, _mm(tuple(tuple(Rn[j][i] for j in range(3)) for i in range(3)), Rn)), (-1.0, None)
    )
    Rn = _lin((1.0, Rn), (-0.5, _mm(Rn, defect)))  # one Newton–Schulz step, as SE3.compose
    Rt = _mv(R, tF)
    pn = tuple(Rt[i] + p[i] for i in range(3))
    zero, one = jnp.zeros_like(pn[0]), jnp.ones_like(pn[0])
    g_next = jnp.stack(
        [jnp.stack([*Rn[i], pn[i]]) for i in range(3)] + [jnp.stack([zero, zero, zero, one])]
    )
    m_next = jnp.stack(m_next)

    converged = norm <= tolerance
    result = jnp.where(converged, RESULTS.successful, RESULTS.newton_not_converged)
    if chart == "exp":
        # Beyond the injectivity radius of exp (rotation angle π) the root is on another branch.
        result = jnp.where(t >= math.pi**2, RESULTS.step_too_large, result)
    ok = jnp.isfinite(norm) & jnp.all(jnp.isfinite(m_next))
    result = jnp.where(ok, result, RESULTS.nonfinite)
    return g_next, m_next, result.astype(jnp.int32), iterations, norm
