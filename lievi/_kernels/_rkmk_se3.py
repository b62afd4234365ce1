"""The fast batched step of the Lie-group Runge–Kutta methods (`RKMK4`, `RKMK5`, `RKMK8`)
for a body on SE(3) (`RigidBodySE3`, any 6×6 kinetic
tensor `M`), free or with a potential linear in the pose (`V = aᵀ g b`, e.g.
`UniformGravitySE3`).

The SE(3) counterpart of `_kernels/_rkmk.py`: an explicit Runge–Kutta method on `(u, m)` in the exponential
chart about the step's start, `g = g_k exp(u)` (`lievi/_integrators/_rkmk.py`), on structure
of arrays — the pose as the 12 entries of `[R | p]`, the momentum `m = (Π, P)` as 6, the
per-run constants the 36 entries of `h M⁻¹` — with the same iterates as the generic step
to round-off (the kernel parity test). Differentiated by JAX's autodiff of these
elementwise operations (no solve inside the step).

With `w = (w_ω, w_v) = h M⁻¹ m` (`h ξ`), a stage's increments are (Kirchhoff's equations,
`lievi.RigidBodySE3`; `lievi.SE3.dexpinv` at `−u`, `u = (u_ω, u_v)`)

    h Π̇ = Π × w_ω + P × w_v,     h Ṗ = P × w_ω,
    h u̇_ω = J⁻¹ w_ω,
    h u̇_v = J⁻¹ w_v + u_v × w_ω/2 + 2c′(t)s u_ω×(u_ω×w_ω) + c (u_ω×(u_v×w_ω) + u_v×(u_ω×w_ω)),

with `J⁻¹ y = y + u_ω×y/2 + c u_ω×(u_ω×y)` (the SO(3) `dexp⁻¹_{−u_ω}`), `c(t)` the
polynomial of `dexp⁻¹`'s series truncated after `ad_u^p` (`_rkmk.dexpinv_coefficient`,
`lievi.SE3.dexpinv_series`: the order-`p` method keeps its order), `t = θ² = |u_ω|²`,
`s = u_ω·u_v` (the lower-left block `∂_v J⁻¹` of `dexpinv`, its coefficient's derivative
along `v` being `2c′(t)s`). The
step's increment `F = exp(u)` is `(exp û_ω, J(u_ω)u_v)` and `g_{k+1} = g_k F`
(`_se3.increment`, `_se3.compose_increment`, the rotation re-orthonormalised as
`lievi.SE3.compose` does).

A potential `V = aᵀ g b` (4-vectors, `a₄`'s term a constant) has the body wrench
`(Γ × b₃, −b₄Γ)` with `Γ = Rᵀa₃` (`V(g exp(εξ)) = aᵀg(1 + εξ̂)b`, so
`dV·ξ = ω·(b₃ × Γ) + b₄ v·Γ`), and at a stage `Γ = exp(u_ω)ᵀΓ_k` (`_rkmk.advected_at`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._groups._series import truncated_dexpinv_terms
from ._base import ones
from ._explicit import explicit_info, finite_result
from ._kick import coupling_torque
from ._rkmk import advected_at, left_dexpinv, scaled_coupling, stored_stages
from ._runge_kutta import CLASSICAL_RK4, ButcherTableau, rk_in_the_chart
from ._se3 import compose_increment, increment
from ._se3_layout import SE3Kernel
from ._soa import cross, dot, entries, horner_with_derivative


def pose_coupling(potential) -> bool:
    """Whether `potential` is linear in the pose, `V = aᵀ g b` with 4-vectors `a`, `b`
    (`AbstractPotential.linear_coupling`)."""
    coupling = potential.linear_coupling()
    return coupling is not None and all(jnp.shape(v)[-1:] == (4,) for v in coupling)


def _stage(u, m, rate, coupling, degree):
    """`(h u̇, h ṁ)` at the stage `(u, m)` (`u = None`: the stage at `u = 0`); `rate`:
    `h M⁻¹`, 6×6; `coupling`: `None`, or `(Γ_k, h b₃, h b₄)` of `V = aᵀ g b`; `degree`:
    of the truncated `dexp⁻¹`."""
    w = tuple(sum(rate[i][j] * m[j] for j in range(6)) for i in range(6))
    wo, wv = w[:3], w[3:]
    Pi, P = m[:3], m[3:]
    spin, drag = cross(Pi, wo), cross(P, wv)
    dPi = tuple(spin[i] + drag[i] for i in range(3))
    dP = cross(P, wo)
    if coupling is not None:
        Gamma, hb3, hb4 = coupling
        if u is not None:
            Gamma = advected_at(u[:3], Gamma)
        torque = coupling_torque(hb3, Gamma)
        dPi = tuple(dPi[i] + torque[i] for i in range(3))
        dP = tuple(dP[i] - hb4 * Gamma[i] for i in range(3))
    if u is None:
        return w, dPi + dP
    uo, uv = u[:3], u[3:]
    c, c1 = horner_with_derivative(truncated_dexpinv_terms(degree), dot(uo, uo))
    du_o, Jwv = left_dexpinv(uo, wo, c), left_dexpinv(uo, wv, c)
    uw = cross(uo, wo)
    uuw, vw = cross(uo, uw), cross(uv, wo)
    vuw, uvw = cross(uv, uw), cross(uo, vw)
    dc = 2 * c1 * dot(uo, uv)
    du_v = tuple(Jwv[i] + vw[i] / 2 + dc * uuw[i] + c * (uvw[i] + vuw[i]) for i in range(3))
    return du_o + du_v, dPi + dP


def rkmk_se3_step(tableau, g, m, rate, coupling=None):
    """One RKMK step with `tableau` on SE(3): `g`: 12 arrays (the rows of `[R | p]`), `m`: 6, `rate`:
    `h M⁻¹`, 6×6 nested arrays or scalars; `coupling`: `None` (free) or `(a, h b)` of
    `V = aᵀ g b` (4-vectors, a batch axis first allowed). Returns `(g_next, m_next, result)`."""
    if coupling is not None:
        a, hb = coupling
        a = jnp.asarray(a, g[0].dtype)
        Gamma = tuple(sum(a[..., i] * g[4 * i + j] for i in range(3)) for j in range(3))
        coupling = (Gamma, hb[..., :3], hb[..., 3])
    one = ones(m[0])
    u, m_next = rk_in_the_chart(
        tableau,
        lambda u, m, c: _stage(u, m, rate, coupling, tableau.dexpinv_degree),
        m,
        stored_stages(one),
    )
    g_next = compose_increment(g, *increment("exp", u[:3], u[3:], one), one)
    return g_next, m_next, finite_result(m_next, g_next)


class RKMKSE3Kernel(SE3Kernel):
    """`rkmk_se3_step` for the Lie-group Runge–Kutta methods (the `tableau`):
    `RigidBodySE3`, free (`potential` `None`) or in a potential linear in the pose
    (`AbstractPotential.linear_coupling`, 4-vectors)."""

    tableau: ButcherTableau = eqx.field(static=True, default=CLASSICAL_RK4)
    potential: eqx.Module | None = None

    def physics(self, system, batched: bool = False):
        if (system.potential is None) != (self.potential is None):
            return None
        if self.potential is not None and not pose_coupling(self.potential):
            return None
        return super().physics(system, batched)

    def constants(self, tensor):
        # M⁻¹ is differentiated (the velocity `M⁻¹m`); of the symmetric part of `M`, as the
        # generic path's `spd_solve`, so that the derivative in `M` is the symmetric one.
        symmetric = (tensor + jnp.swapaxes(tensor, -1, -2)) / 2
        return entries(tensor), entries(jnp.linalg.inv(symmetric))

    def prepare(self, constants, h):
        rate = tuple(tuple(h * e for e in row) for row in constants[1])
        return rate, scaled_coupling(self.potential, h)

    def step(self, params, g, m, alive):
        g_next, m_next, result = rkmk_se3_step(self.tableau, g, m, *params)
        return (g_next, m_next, result, *explicit_info(m))
