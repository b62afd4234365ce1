"""Hand-written tangents of the explicit fast steps (`_kernels/_explicit.py`).

Plain autodiff of `splitting_step` differentiates the polynomial `sincos` term by term,
and the 3×3 products that compose the five sub-flows entry by entry. Here each step is a
`jax.custom_jvp` whose tangent is written out from the structure of the method: linear
in the tangents, with coefficients the backward pass recomputes cheaply from the step's
input (`simulate_batch` keeps only that, `jax.checkpoint`), and JAX transposes it for
reverse mode; forward mode (`jax.jvp`, `jax.jacfwd`) keeps working. The tests compare
both modes with plain autodiff of the same arithmetic (`_explicit_primal.splitting_primal`,
`rk4_primal`).

**Splitting** (paper §6). The five sub-flows are rotations `F_j = exp(α_j ê_{p_j})` with
`α_j = f_j Π_{p_j}^{(j−1)} R_{p_j}` (`R = h/I`), `Π^{(j)} = F_jᵀ Π^{(j−1)}` and
`g' = g F`, `F = F_1⋯F_5`. Since `∂F_j/∂α_j = ê_p F_j = F_j ê_p`,

    dα_j = f_j (dΠ_p^{(j−1)} R_p + Π_p^{(j−1)} dR_p),
    dΠ^{(j)} = F_jᵀ dΠ^{(j−1)} − (e_p × Π^{(j)}) dα_j,
    dg' = (dg + g ŵ) F,   w = Σ_j dα_j F_1⋯F_{j−1} e_{p_j}

(`dF = ŵ F`, `ŵ` the hat map), `w` accumulated from the inside out. The derivative of
each sine and cosine is the other one (no polynomial is differentiated), the momenta's
tangents rotate as 2×2 blocks, and `dg'` reuses the step's own `F` (rebuilt from the
quaternion the step stores, `_explicit_primal.splitting_primal`).

**RK4**. The step depends on `h` and `I` only through the ratios `h/I_p` (`rk4_step`):
with `w_i = (h/I)·Π_i`, the stages are `k_i = f(y_i) = (g_i ŵ_i, Π_i × w_i)`,
`y_{i+1} = y + c_i k_i`, `y' = y + (k_1 + 2k_2 + 2k_3 + k_4)/6`. The tangent is the same
Runge–Kutta step on the variational equation,

    dk_i = (dg_i ŵ_i + g_i dŵ_i, dΠ_i × w_i + Π_i × dw_i),   dw_i = (h/I)·dΠ_i + Π_i·d(h/I),

three parameter tangents (not four: `h` and `I⁻¹` apart), so reverse mode accumulates
three cotangents a step and the backward pass has one fewer output that depends on every
stage.
"""

from __future__ import annotations

import jax

from . import _explicit_primal


@jax.custom_jvp
def splitting_flow(g, m, rate):
    """`(g_next, Π_next)` of one splitting step, as `_explicit.splitting_step`."""
    g_next, m_next, *_ = _explicit_primal.splitting_primal(g, m, rate)
    return g_next, m_next


@splitting_flow.defjvp
def _splitting_flow_jvp(primals, tangents):
    g, m, R = primals
    dg, dm, dR = tangents
    g_next, m_next, rotations, momenta, F = _explicit_primal.splitting_primal(g, m, R)
    subflows = _explicit_primal.SUBFLOWS
    dm = list(dm)
    dalpha = []
    for (p, fraction), (c, s), before, after in zip(subflows, rotations, momenta, momenta[1:]):
        q, r = (p + 1) % 3, (p + 2) % 3
        da = fraction * (dm[p] * R[p] + before[p] * dR[p])
        dm[q], dm[r] = (
            c * dm[q] + s * dm[r] + after[r] * da,
            c * dm[r] - s * dm[q] - after[q] * da,
        )
        dalpha.append(da)
    # w = Σ_j dα_j F_1⋯F_{j−1} e_{p_j}, inside out: u ← F_j u + dα_j e_{p_j}.
    w = [0.0, 0.0, 0.0]
    w[subflows[-1][0]] = dalpha[-1]
    for j in reversed(range(len(subflows) - 1)):
        p = subflows[j][0]
        w = _rotate(p, *rotations[j], w)
        w[p] = w[p] + dalpha[j]
    # dg' = (dg + g ŵ) F, row by row (`x ŵ = x × w`).
    rows = []
    for i in range(len(g) // 3):
        gw = cross(g[3 * i : 3 * i + 3], w)
        rows += [dg[3 * i + k] + gw[k] for k in range(3)]
    return (g_next, m_next), (_explicit_primal.matmul3(tuple(rows), F), tuple(dm))


def _rotate(p, c, s, v):
    """`F v` for the rotation `F = exp(α ê_p)` with `(c, s) = (cos α, sin α)` (`Fᵀ v` for
    `−s`); `v` a list of 3, entries may be Python zeros."""
    q, r = (p + 1) % 3, (p + 2) % 3

    def combine(a, x, b, y):  # a x + b y, dropping Python zeros
        terms = [t * z for t, z in ((a, x), (b, y)) if not (isinstance(z, float) and z == 0)]
        return sum(terms[1:], terms[0]) if terms else 0.0

    v = list(v)
    v[q], v[r] = combine(c, v[q], -s, v[r]), combine(s, v[q], c, v[r])
    return v


def cross(x, y):
    return (x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0])


@jax.custom_jvp
def rk4_flow(g, m, rate):
    """`(g_next, Π_next)` of one RK4 step, as `_explicit.rk4_step`."""
    g_next, m_next, _ = _explicit_primal.rk4_primal(g, m, rate)
    return g_next, m_next


@rk4_flow.defjvp
def _rk4_flow_jvp(primals, tangents):
    g, m, rate = primals
    dg, dm, drate = tangents
    g_next, m_next, stages = _explicit_primal.rk4_primal(g, m, rate)
    slopes = []
    for c, ((gi, Pii), _, w) in zip((None, 0.5, 0.5, 1.0), stages):
        if c is None:
            dgi, dPii = dg, dm
        else:
            dkg, dkP = slopes[-1]
            dgi = tuple(d + c * dk for d, dk in zip(dg, dkg))
            dPii = tuple(d + c * dk for d, dk in zip(dm, dkP))
        dw = tuple(dPii[i] * rate[i] + Pii[i] * drate[i] for i in range(3))
        dkP = tuple(a + b for a, b in zip(cross(dPii, w), cross(Pii, dw)))
        dkg = []
        for i in range(len(g) // 3):
            a = cross(dgi[3 * i : 3 * i + 3], w)
            b = cross(gi[3 * i : 3 * i + 3], dw)
            dkg += [a[k] + b[k] for k in range(3)]
        slopes.append((tuple(dkg), dkP))

    def combine(dx, part):
        return tuple(
            d + (t[0] + 2 * t[1] + 2 * t[2] + t[3]) / 6
            for d, t in zip(dx, zip(*(dk[part] for dk in slopes)))
        )

    return (g_next, m_next), (combine(dg, 0), combine(dm, 1))
