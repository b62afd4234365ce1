"""The fast batched step of the Lie-group Runge–Kutta methods (`RKMK4`, `RKMK5`, `RKMK8`)
for the rigid body with principal moments, free or with a potential linear in `g`
(`V = aᵀ g b`, e.g. uniform gravity: the heavy top).

The structure-of-arrays counterpart of `lievi/_integrators/_rkmk.py` (an explicit
Runge–Kutta method on `(u, Π)` with `g = g_k exp(u)`, its tableau a static field), as
`_explicit.py` is for `RK4`: every component its own `(B,)` array, closed forms, and the same iterates as the generic step to round-off (the
kernel parity test). Differentiated by JAX's autodiff of these elementwise operations.

With `w = (h/I)·Π` (the angle turned per step at momentum `Π`) the stage increments are

    h u̇ = dexp⁻¹_{−u}(w) = w + u×w/2 + c(θ) u×(u×w),     h Π̇ = Π × w,

`c(θ²)` (`θ = |u|`) the polynomial of `dexp⁻¹`'s commutator series truncated after
`ad_u^p` for a tableau of order `p` (`ButcherTableau.dexpinv_degree`,
`lievi.SO3.dexpinv_series`): `1/12 + θ²/720` for `RKMK4` and `RKMK5`,
`1/12 + θ²/720 + θ⁴/30240 + θ⁶/1209600` for `RKMK8` — the first terms of the exact
`(1 − (θ/2)cot(θ/2))/θ²`; the method keeps its order, and a stage costs a few
multiply-adds instead of two series and a division. The increment `F = exp(u)` is
Rodrigues' `1 + a û + b û²`, `a = sin θ/θ`, `b = (1 − cos θ)/θ²`, from power series in
`θ²/4` accurate to round-off on the method's whole step range. With a potential `V = aᵀ g b` the torque `Γ × b` at a stage is that of
`Γ = (g_k exp(u))ᵀa = exp(u)ᵀ Γ_k = Γ_k − α u×Γ_k + β u×(u×Γ_k)` (`α`, `β` as `a`, `b`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._groups._series import truncated_dexpinv_terms
from ._base import AbstractBatchKernel, materialise, ones, per_run
from ._explicit import explicit_info, finite_result
from ._kick import advected_rows, coupling_torque, rigid_body_coupling
from ._runge_kutta import CLASSICAL_RK4, ButcherTableau, rk_in_the_chart
from ._soa import C_SERIES, S_SERIES, cross, dot, horner, rotate_rows


def _rotation_coefficients(t):
    """`(sin θ/θ, (1 − cos θ)/θ²)` at `t = θ²`."""
    S, C = horner(S_SERIES, t / 4), horner(C_SERIES, t / 4)
    return S * C, S * S / 2


def advected_at(u, Gamma):
    """`Γ = (g_k exp(u))ᵀa = exp(u)ᵀΓ_k` at a stage, from `Γ_k = g_kᵀa`."""
    alpha, beta = _rotation_coefficients(dot(u, u))
    uG = cross(u, Gamma)
    uuG = cross(u, uG)
    return tuple(Gamma[i] - alpha * uG[i] + beta * uuG[i] for i in range(3))


def dexpinv_coefficient(u, degree):
    """`c(θ²)` at `θ = |u|` of `dexp⁻¹`'s series truncated after `ad_u^degree`
    (`lievi.SO3.dexpinv_series`)."""
    return horner(truncated_dexpinv_terms(degree), dot(u, u))


def left_dexpinv(u, w, c):
    """`dexp⁻¹_{−u}(w) = w + u×w/2 + c u×(u×w)` on SO(3) (`c = dexpinv_coefficient(u, …)`;
    the `ad_u` term present for any degree ≥ 1, as the methods' orders ≥ 4 have)."""
    uw = cross(u, w)
    uuw = cross(u, uw)
    return tuple(w[i] + uw[i] / 2 + c * uuw[i] for i in range(3))


def _stage(u, m, rate, coupling, degree):
    """`(h u̇, h Π̇)` at the stage `(u, Π)` (`u = None`: the stage at `u = 0`).
    `coupling`: `None`, or `(Γ_k, h b)` of a potential `V = aᵀ g b`; `degree`: of the
    truncated `dexp⁻¹`."""
    w = tuple(rate[i] * m[i] for i in range(3))
    dm = cross(m, w)
    if coupling is not None:
        Gamma, hb = coupling
        if u is not None:
            Gamma = advected_at(u, Gamma)
        torque = coupling_torque(hb, Gamma)
        dm = tuple(dm[i] + torque[i] for i in range(3))
    if u is None:
        return w, dm
    return left_dexpinv(u, w, dexpinv_coefficient(u, degree)), dm


def scaled_coupling(potential, h):
    """`(a, h b)` of a potential `V = aᵀ g b` (`AbstractPotential.linear_coupling`), or
    `None` without one: once per run (`prepare`), not per step. `h` per body scales `b`
    per body."""
    if potential is None:
        return None
    a, b = potential.linear_coupling()
    return a, h[..., None] * b if jnp.ndim(h) else h * b


def stored_stages(one):
    """The `store` of `rk_in_the_chart` for the kernels: each stage's inputs and
    increments kept (`_base.materialise` with its run-time `one`), read where needed
    rather than recomputed in each reader (measured: 1.7–1.8× the body-steps/s of
    `RKMK4`, and the order-8 method's gradient compiled in 13 s where it had not finished
    in 10 minutes)."""

    def store(du, dm):
        values = materialise(tuple(du) + tuple(dm), one)
        return values[: len(du)], values[len(du) :]

    return store


def rkmk_step(tableau, g, m, rate, coupling=None):
    """One RKMK step with `tableau`: `g`: 9 arrays (row-major), `m`: 3 arrays, `rate`:
    `h/I_p`, 3 arrays or scalars; `coupling`: `None` (free) or `(a, h b)` of `V = aᵀ g b`.
    Returns `(g_next, m_next, result)`."""
    if coupling is not None:
        coupling = (advected_rows(coupling[0], g), coupling[1])
    one = ones(m[0])
    u, m_next = rk_in_the_chart(
        tableau,
        lambda u, m, c: _stage(u, m, rate, coupling, tableau.dexpinv_degree),
        m,
        stored_stages(one),
    )
    # g exp(u), Rodrigues' coefficients. `u = Σ b_j k_j` and the coefficients are stored
    # once: each of the 9 entries of `g_{k+1}` reads them, and would otherwise recompute
    # the sum and the series (measured: 1.2–1.3× the body-steps/s of `RKMK8`).
    *u, a, b = materialise((*u, *_rotation_coefficients(dot(u, u))), one)
    g_next = rotate_rows(g, u, a, b)
    return g_next, m_next, finite_result(m_next, g_next)


class RKMKKernel(AbstractBatchKernel):
    """`rkmk_step` for the Lie-group Runge–Kutta methods (`RKMK4`, `RKMK5`, `RKMK8`: the
    `tableau`): the rigid body with principal moments, free (`potential` `None`) or in a
    potential linear in `g` (`AbstractPotential.linear_coupling`)."""

    tableau: ButcherTableau = eqx.field(static=True, default=CLASSICAL_RK4)
    potential: eqx.Module | None = None

    def physics(self, system, batched: bool = False):
        if (system.potential is None) != (self.potential is None):
            return None
        if self.potential is not None and not rigid_body_coupling(self.potential):
            return None
        return super().physics(system, batched)

    def prepare(self, inertia, h):
        return per_run([h / moment for moment in inertia]), scaled_coupling(self.potential, h)

    def advected(self, state):
        # `Γ = gᵀa` of `V = aᵀ g b` from the carried `g` (`save=("m", "advected")`).
        if self.potential is None:
            return None
        return advected_rows(self.potential.linear_coupling()[0], state)

    def step(self, params, g, m, alive):
        g_next, m_next, result = rkmk_step(self.tableau, g, m, *params)
        return (g_next, m_next, result, *explicit_info(m))
