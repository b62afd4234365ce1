"""Hand-written derivatives of the explicit fast steps (`_fast_explicit.py`).

Plain autodiff of `splitting_step` differentiates the polynomial `sincos` term by term
and, under the per-step `jax.checkpoint` of `simulate_batch`, re-evaluates it in the
backward pass; plain autodiff of `rk4_step` transposes every stage through XLA-fused
elementwise code that recomputes shared producers many times over. Here each step is a
`jax.custom_jvp` whose tangent is written out from the structure of the method, linear in
the tangents with coefficients that are cheap to recompute from the step's input and the
few values it saves (`ROOT_NAME`); JAX transposes it for reverse mode, and forward mode
(`jax.jvp`, `jax.jacfwd`) keeps working.

**Splitting** (paper §6). The five sub-flows are rotations `F_j = exp(α_j ê_{p_j})` with
`α_j = f_j Π_{p_j}^{(j−1)} / A_{p_j}` (`A = I/h`), `Π^{(j)} = F_jᵀ Π^{(j−1)}` and
`g' = g F`, `F = F_1⋯F_5`. Since `∂F_j/∂α_j = ê_p F_j`,

    dα_j = f_j (dΠ_p^{(j−1)} − Π_p^{(j−1)} dA_p / A_p) / A_p,
    dΠ^{(j)} = F_jᵀ dΠ^{(j−1)} − (e_p × Π^{(j)}) dα_j,
    dg' = (dg + g ŵ) F,   w = Σ_j dα_j F_1⋯F_{j−1} e_{p_j},

(`dF = ŵ F`, `ŵ` the hat map), `w` accumulated from the inside out. The sines and
cosines are the forward pass's, saved: the backward pass evaluates no polynomial, and
the rotations `F_j` act as 2×2 blocks (no 3×3 products, `F` itself is never formed).

**RK4**: the tangent of a Runge–Kutta step is the same Runge–Kutta step on the
variational equation, `dk_i = ∂f(y_i)[dy_i] + ∂f/∂I⁻¹ dI⁻¹`, with the stage increments
`dy_i = dy + c_i (h dk_{i−1} + dh k_{i−1})`; for `f(g, Π) = (g Ω̂, Π × Ω)`, `Ω = I⁻¹Π`:
`∂f[dg, dΠ] = (dg Ω̂ + g dΩ̂, dΠ × Ω + Π × dΩ)`, `dΩ = I⁻¹dΠ + dI⁻¹ Π`.
"""

from __future__ import annotations

import jax

# A module import: `_fast_explicit` imports this module too (its steps call the rules).
from . import _fast_explicit

# (axis, fraction of h) of the palindromic splitting, as `_splitting.py`.
SUBFLOWS = ((0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5))


@jax.custom_jvp
def splitting_flow(g, Pi, inertia_over_h):
    """`(g F, Fᵀ⋯)` of one splitting step: `(g_next, Π_next)` as `_fast_explicit.splitting_step`."""
    g_next, Pi_next, _, _ = _fast_explicit.splitting_primal(g, Pi, inertia_over_h)
    return g_next, Pi_next


@splitting_flow.defjvp
def _splitting_flow_jvp(primals, tangents):
    g, Pi, A = primals
    dg, dPi, dA = tangents
    g_next, Pi_next, rotations, momenta = _fast_explicit.splitting_primal(g, Pi, A)
    dPi = list(dPi)
    dalpha = []
    for (p, fraction), (c, s), before, after in zip(SUBFLOWS, rotations, momenta, momenta[1:]):
        q, r = (p + 1) % 3, (p + 2) % 3
        da = fraction * (dPi[p] - before[p] / A[p] * dA[p]) / A[p]
        dPi[q], dPi[r] = (
            c * dPi[q] + s * dPi[r] + after[r] * da,
            c * dPi[r] - s * dPi[q] - after[q] * da,
        )
        dalpha.append(da)
    # w = Σ_j dα_j F_1⋯F_{j−1} e_{p_j}, inside out: u ← F_j u + dα_j e_{p_j}.
    w = [0.0, 0.0, 0.0]
    w[SUBFLOWS[-1][0]] = dalpha[-1]
    for j in reversed(range(len(SUBFLOWS) - 1)):
        p = SUBFLOWS[j][0]
        w = _rotate(p, *rotations[j], w)
        w[p] = w[p] + dalpha[j]
    # dg' = (dg + g ŵ) F_1⋯F_5, row by row (`x ŵ = x × w`; `x F_j = (F_jᵀ xᵀ)ᵀ`).
    dg_next = []
    for i in range(len(g) // 3):
        gw = _cross(g[3 * i : 3 * i + 3], w)
        row = [dg[3 * i + k] + gw[k] for k in range(3)]
        for (p, _), (c, s) in zip(SUBFLOWS, rotations):
            row = _rotate(p, c, -s, row)
        dg_next += row
    return (g_next, Pi_next), (tuple(dg_next), tuple(dPi))


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


def _cross(x, y):
    return (x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0])


@jax.custom_jvp
def rk4_flow(g, Pi, h, inverse_inertia):
    """`(g_next, Π_next)` of one RK4 step, as `_fast_explicit.rk4_step`."""
    g_next, Pi_next, _ = _fast_explicit.rk4_primal(g, Pi, h, inverse_inertia)
    return g_next, Pi_next


@rk4_flow.defjvp
def _rk4_flow_jvp(primals, tangents):
    g, Pi, h, inverse_inertia = primals
    dg, dPi, dh, d_inverse_inertia = tangents
    g_next, Pi_next, stages = _fast_explicit.rk4_primal(g, Pi, h, inverse_inertia, barrier=True)
    dy = (dg, dPi)
    slopes = []
    for c, ((gi, Pii), _) in zip((None, 0.5, 0.5, 1.0), stages):
        if c is None:
            dyi = dy
        else:
            (kg, kP), dk = stages[len(slopes) - 1][1], slopes[-1]
            dyi = tuple(
                tuple(d + c * (h * dki + dh * ki) for d, dki, ki in zip(dx, dkx, kx))
                for dx, dkx, kx in zip(dy, dk, (kg, kP))
            )
        w = tuple(Pii[i] * inverse_inertia[i] for i in range(3))
        dw = tuple(dyi[1][i] * inverse_inertia[i] + Pii[i] * d_inverse_inertia[i] for i in range(3))
        dkP = tuple(a + b for a, b in zip(_cross(dyi[1], w), _cross(Pii, dw)))
        dkg = []
        for i in range(len(g) // 3):
            a = _cross(dyi[0][3 * i : 3 * i + 3], w)
            b = _cross(gi[3 * i : 3 * i + 3], dw)
            dkg += [a[k] + b[k] for k in range(3)]
        slopes.append((tuple(dkg), dkP))
    k = [s for _, s in stages]

    def combine(x, dx, part):
        terms = [dk[part] for dk in slopes]
        slope = [ki[part] for ki in k]
        return tuple(
            d
            + h / 6 * (t[0] + 2 * t[1] + 2 * t[2] + t[3])
            + dh / 6 * (s[0] + 2 * s[1] + 2 * s[2] + s[3])
            for d, t, s in zip(dx, zip(*terms), zip(*slope))
        )

    return (g_next, Pi_next), (combine(g, dg, 0), combine(Pi, dPi, 1))
