"""The SE(3) DEP equation with the velocity eliminated: `ρ(ω) = r_ω(ω, v(ω))` and its 3×3
Jacobian, the Schur complement of the 6×6 one, in structure of arrays (paper (4.8) on
SE(3)). The residual's translation block `r_v = K′(ω)(A₂₁ω + A₂₂v) − P` is linear in `v`,
so for a given `ω` it is solved in closed form (`velocity_part`); the Newton iteration of
`_se3.py` then runs on the rotation part alone (`reduced_residual`). Blocks and
coefficients as in `_se3_residual.py`.
"""

from __future__ import annotations

from ._base import materialise, ones
from ._se3_residual import e_blocks, exp_series, mv, operator
from ._soa import cross, dot, matmul


def velocity_part(chart, w, m, C, series=None):
    """`(q, v)` with `r_v(ω, v) = 0`: `q = b = K′(ω)⁻¹P`, `v = A₂₂⁻¹(q − A₂₁ω) = A₂₂⁻¹q − Tω`.

    `K′⁻¹`: Cayley `(1 + ω̂/2)⁻¹ y = (y − ω×y/2 + ω(ω·y)/4)/(1 + t/4)`; exp
    `(1 + ω̂/2 + c ω̂²)⁻¹ = 1 − β ω̂ + γ ω̂²`, `β = (1 − cos θ)/θ²`, `γ = (θ − sin θ)/θ³`
    (the inverse of the SO(3) `dexpinv`, i.e. `dexp(−ω)`).
    """
    _, _, A22inv, T = C
    P = m[3:]
    t = dot(w, w)
    wP, oP = cross(w, P), dot(w, P)
    if chart == "cayley":
        scale = 1 / (1 + t / 4)
        q = tuple((P[i] - wP[i] / 2 + w[i] * oP / 4) * scale for i in range(3))
    else:
        beta, gamma = (exp_series(t) if series is None else series)[3:]
        q = tuple(P[i] - beta * wP[i] + gamma * (w[i] * oP - t * P[i]) for i in range(3))
    A22q, Tw = mv(A22inv, q), mv(T, w)
    v = tuple(A22q[i] - Tw[i] for i in range(3))
    return q, v


def reduced_residual(chart, w, m, C, with_jacobian: bool):
    """The DEP equation with `v` eliminated: `ρ(ω) = r_ω(ω, v(ω))` where `v(ω)` solves
    `r_v = K′(ω)(A₂₁ω + A₂₂v) − P = 0` exactly (`velocity_part`), and, if asked, its 3×3
    Jacobian, the Schur complement `J₁₁ − J₁₂J₂₂⁻¹J₂₁` of the 6×6 one (`residual`):

        dρ/dω = K(S + ZQ) + E_ωv V + E_ωω + L Q,   Q = dq/dω = −K′⁻¹E_vω,
        V = dv/dω = A₂₂⁻¹Q − T,

    with the blocks `E` of `∂(dφ⁻¹(ξ)ᵀμ)/∂ξ` at fixed `μ = (a, q)` (`residual`) and the
    per-run constants `S = A₁₁ − A₁₂A₂₂⁻¹A₂₁`, `Z = A₁₂A₂₂⁻¹`, `T = A₂₂⁻¹A₂₁` (`C`), so
    that `K A₁₁ + K A₁₂V = K(S + ZQ)` and `a = A₁₁ω + A₁₂v = Sω + Zq`. Newton on `ρ` is
    Newton on the 6×6 system with `v` re-solved after each step: the same root (the one
    the generic path converges to from the explicit-Euler guess), a 3×3 solve.
    Returns `(ρ, J, (q, v))`.
    """
    S, Z, A22inv, T = C
    one = ones(w[0])
    series = None
    if chart == "exp":
        series = exp_series(dot(w, w))
        if with_jacobian:
            # Not stacked for one body: stacked, this group made the exp step under
            # `jax.vmap(simulate)` 30× slower (XLA's fusion of the stacked Horner chains;
            # measured 6.5 against 0.22 µs a body-step), for 5 % on one body.
            series = materialise(series, one, stack=False)
    q, v = velocity_part(chart, w, m, C, series)
    if with_jacobian:
        q, v = materialise(q, one), materialise(v, one)
    # a = A₁₁ω + A₁₂v = Sω + Zq.
    Sw, Zq = mv(S, w), mv(Z, q)
    a = tuple(Sw[i] + Zq[i] for i in range(3))
    if chart == "cayley":
        return _reduced_cayley(w, m, C, q, v, a, with_jacobian, one)
    K, L, Kp, coefficients = operator(chart, w, v, None if series is None else series[:3])
    Ka, Lq = mv(K, a), mv(L, q)
    rho = tuple(Ka[i] + Lq[i] - m[i] for i in range(3))
    if not with_jacobian:
        return rho, None, (q, v)
    E_ww, E_wv, E_vw = e_blocks(chart, w, v, a, q, m[3:], coefficients)
    # Q = −K′⁻¹ E_vω, column by column (K′⁻¹ as `velocity_part`).
    t = dot(w, w)
    columns = []
    for j in range(3):
        y = tuple(-E_vw[i][j] for i in range(3))
        wy, oy = cross(w, y), dot(w, y)
        if chart == "cayley":
            scale = 1 / (1 + t / 4)
            columns.append(tuple((y[i] - wy[i] / 2 + w[i] * oy / 4) * scale for i in range(3)))
        else:
            beta, gamma = series[3:]
            columns.append(
                tuple(y[i] - beta * wy[i] + gamma * (w[i] * oy - t * y[i]) for i in range(3))
            )
    Q = tuple(tuple(columns[j][i] for j in range(3)) for i in range(3))
    # K A₁₁ + K A₁₂V = K(S + ZQ), V = A₂₂⁻¹Q − T.
    ZQ, A22Q = matmul(Z, Q), matmul(A22inv, Q)
    U = tuple(tuple(S[i][j] + ZQ[i][j] for j in range(3)) for i in range(3))
    V = tuple(tuple(A22Q[i][j] - T[i][j] for j in range(3)) for i in range(3))
    KU, EV, LQ = matmul(K, U), matmul(E_wv, V), matmul(L, Q)
    J = tuple(
        tuple(KU[i][j] + EV[i][j] + E_ww[i][j] + LQ[i][j] for j in range(3)) for i in range(3)
    )
    return rho, J, (q, v)


def _reduced_cayley(w, m, C, q, v, a, with_jacobian, one):
    """`reduced_residual` for the Cayley chart, where `L q = v × K′q/2 = v × P/2`:

        ρ = K a + v × P/2 − Π,
        dρ/dω = −â/2 + (ω·a)/4 + ωaᵀ/4 + K(S + ZQ) − P̂V/2,
        V = dv/dω = A₂₂⁻¹Q − T,   Q = dq/dω = K′⁻¹ q̂/2

    (`K′q = P` ⇒ `dK′ q + K′ dq = 0`, `dK′ q = dω × q/2`).
    """
    S, Z, A22inv, T = C
    Pi, P = m[:3], m[3:]
    wa, oa = cross(w, a), dot(w, a)
    vP = cross(v, P)
    rho = tuple(a[i] + wa[i] / 2 + w[i] * oa / 4 + vP[i] / 2 - Pi[i] for i in range(3))
    if not with_jacobian:
        return rho, None, (q, v)
    t = dot(w, w)
    scale = 1 / (1 + t / 4)
    W = ((0, -w[2], w[1]), (w[2], 0, -w[0]), (-w[1], w[0], 0))
    Kpi = tuple(
        tuple((((1 if i == j else 0) - W[i][j] / 2 + w[i] * w[j] / 4) * scale) for j in range(3))
        for i in range(3)
    )
    qh = ((0, -q[2], q[1]), (q[2], 0, -q[0]), (-q[1], q[0], 0))
    # Q = K′⁻¹ q̂/2 (q̂ has a zero diagonal).
    Q = tuple(
        tuple(sum(Kpi[i][k] * qh[k][j] for k in range(3) if k != j) / 2 for j in range(3))
        for i in range(3)
    )
    # K A₁₁ + K A₁₂V = K(S + ZQ); −P̂V/2 with V = A₂₂⁻¹Q − T.
    ZQ, A22Q = matmul(Z, Q), matmul(A22inv, Q)
    U = tuple(tuple(S[i][j] + ZQ[i][j] for j in range(3)) for i in range(3))
    V = tuple(tuple(A22Q[i][j] - T[i][j] for j in range(3)) for i in range(3))
    K = tuple(
        tuple((1 if i == j else 0) + W[i][j] / 2 + w[i] * w[j] / 4 for j in range(3))
        for i in range(3)
    )
    KU = matmul(K, U)
    Ph = ((0, -P[2], P[1]), (P[2], 0, -P[0]), (-P[1], P[0], 0))
    Ah = ((0, -a[2], a[1]), (a[2], 0, -a[0]), (-a[1], a[0], 0))
    J = tuple(
        tuple(
            KU[i][j]
            - sum(Ph[i][k] * V[k][j] for k in range(3) if k != i) / 2
            - Ah[i][j] / 2
            + w[i] * a[j] / 4
            + (oa / 4 if i == j else 0)
            for j in range(3)
        )
        for i in range(3)
    )
    return rho, J, (q, v)
