"""The discrete Euler–Poincaré / discrete Lie–Poisson integrator (paper §2–§4, (4.8); §7).

Discrete Lagrangian, in a chart `φ` of the group: `exp` as in (4.7), or the Cayley map
`cay`, the choice the paper discusses after (5.7), second order by Lewis–Simo [LS 96]:

- left-invariant (the rigid body): `L_d(g_k, g_{k+1}) = h·l(φ⁻¹(g_k⁻¹ g_{k+1})/h)`;
- right-invariant: `L_d(g_k, g_{k+1}) = h·l(φ⁻¹(g_{k+1} g_k⁻¹)/h)`.

Writing `F_k = φ(ξ_k)` for the increment and `dφ⁻¹` for the inverse of the
right-trivialised derivative of `φ`, the DEP equation (2.4)/(2.5), i.e. (4.8) for the
exponential chart, becomes in momentum form (docs/theory/conventions.md)

    left:  Π_k = dφ⁻¹(ξ_k)ᵀ ∇l(ξ_k/h),        Π_{k+1} = Ad_{F_k}ᵀ Π_k    (DLP, 3.3),
                                             g_{k+1} = g_k F_k           (2.9);
    right: μ_k = dφ⁻¹(−ξ_k)ᵀ ∇l(ξ_k/h),       μ_{k+1} = Ad_{F_k⁻¹}ᵀ μ_k   (DLP, 3.2),
                                             g_{k+1} = F_k g_k            (2.8).

With a potential `V(g)` (paper §7; `L(g, ξ) = l(ξ) − V(g)`) the discrete Lagrangian is

    L_d(g_k, g_{k+1}) = h·l(φ⁻¹(g_k⁻¹ g_{k+1})/h) − (h/2)(V(g_k) + V(g_{k+1})),

the Lie group variational integrator of Lee, Leok and McClamroch (there for the exponential
chart on SO(3)). Its discrete Legendre transforms `Π_k = −D₁L_d`, `Π_{k+1} = D₂L_d`
(trivialised on the side of the symmetry) pick up `± (h/2) dV`, so with `M = −dV` the
generalised force (the body torque; `AbstractLieSystem.force`) the step reads, left-invariant,

    Π_k⁺ = Π_k + (h/2) M(g_k),                          (kick)
    Π_k⁺ = dφ⁻¹(ξ_k)ᵀ ∇l(ξ_k/h),   F_k = φ(ξ_k),      (the free DEP equation above)
    g_{k+1} = g_k F_k,   Π_{k+1} = Ad_{F_k}ᵀ Π_k⁺ + (h/2) M(g_{k+1})        (kick),

and the same with the right-trivialised force for right-invariant systems: the free step
between two half kicks (`AbstractKickIntegrator`). When `V` depends on `g` only through an
advected vector, e.g. the vertical `Γ = gᵀe₃` of a heavy top, the pair `(Π_k, Γ_k)` with
`Γ_{k+1} = F_kᵀ Γ_k` evolves on its own: the discrete reduction of the paper's §7
(Bobenko–Suris), and `|Γ|²` and `Π·Γ` are conserved exactly.

The implicit equation for `ξ_k` is solved by Newton's method (`_newton.py`); the
momentum update and reconstruction are explicit. The momentum is advanced by the
coadjoint action, so it stays on its coadjoint orbit: Casimirs are kept to round-off.

Sign convention. For right-invariant systems the paper's (4.7) uses
`log(g_k g_{k+1}⁻¹) ≈ −h ξ`; we use `g_{k+1} g_k⁻¹ ≈ exp(h ξ)` so that `ξ` approximates the
right velocity `ġg⁻¹` and `l` is evaluated at the velocity, not its negative. The two agree
for Lagrangians even in `ξ` (all quadratic ones). The right-invariant run of `(g_k, μ_k)`
equals the left-invariant run of `(g_k⁻¹, −μ_k)` for `l̃(ξ) = l(−ξ)`; the tests check this.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._checks import as_int
from .._groups._charts import AbstractChart, as_chart
from .._kernels._se3 import SE3NewtonKernel
from .._kernels._so3 import NewtonKernel
from .._kernels._so3_equations import DEPEquation
from .._newton import check_newton_options, newton_solve, newton_tolerance
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from ._base import AbstractVariationalIntegrator, StepInfo


class DEP(AbstractVariationalIntegrator):
    """Discrete Euler–Poincaré integrator with the discrete Lie–Poisson update.

    Second order for both charts (the paper leaves the exponential chart open at the end
    of §5; the convergence tests answer it). Symplectic on `G × G`, Lie–Poisson on `g*`,
    momentum-preserving.

    **Arguments:**

    - `chart`: `"exp"` (the paper's (4.7)–(4.8)) or `"cayley"` (the same DEP equation with
      `F_k = cay(ξ_k)`, the Cayley variant discussed after (5.7)). Note that the
      Moser–Veselov/Lewis–Simo scheme (5.7) itself uses a different discrete Lagrangian,
      `tr((I − F)Λ)/h` (on SO(3): `½ξᵀIξ / (h(1 + |ξ|²/4))` with `F = cay(ξ)`), so its
      iterates differ from these at O(h³) per step.
    - `rtol`, `atol`: the Newton solve stops when `‖residual‖_∞ ≤ atol + rtol·‖m‖_∞`
      (momentum units). Default: `rtol` = 64 ulps of the dtype, `atol` = 0 — a relative
      test, so the computed trajectory does not depend on the units (see
      `lievi._newton.newton_tolerance`).
    - `max_steps`: maximum Newton iterations per step; exceeding it is reported as
      `RESULTS.newton_not_converged`.
    """

    chart: AbstractChart = eqx.field(default="exp", static=True, converter=as_chart)
    rtol: float | None = eqx.field(default=None, static=True)
    atol: float | None = eqx.field(default=None, static=True)
    max_steps: int = eqx.field(default=20, static=True, converter=as_int)

    def __check_init__(self):
        check_newton_options(self.max_steps, self.rtol, self.atol)

    def order(self) -> int:
        return 2

    def is_symmetric(self) -> bool:
        # The adjoint Lagrangian −L_d(g_{k+1}, g_k; −h) equals L_d: φ⁻¹(F⁻¹) = −φ⁻¹(F).
        return True

    def own_step(self) -> bool:
        # The kernels and the step cache compute this class's own step (not a subclass's).
        return type(self) is DEP

    def kernels(self):
        # Closed forms for the rigid body with principal moments, and for any free body on SE(3).
        options = (self.chart, self.rtol, self.atol, self.max_steps)
        return NewtonKernel(DEPEquation(self.chart), *options[1:]), SE3NewtonKernel(*options)

    def kinetic_discrete_lagrangian(self, system: AbstractLieSystem, g0, g1, h: Scalar) -> Scalar:
        group = system.group
        increment = system.side.increment(group, g0, g1)
        return h * system.lagrangian(self.chart.inverse(group, increment) / h)

    def residual(self, system: AbstractLieSystem, m: Float[Array, " d"], h: Scalar):
        """`ξ ↦ dφ⁻¹(±ξ)ᵀ ∇l(ξ/h) − m`: the DEP equation (4.8) in momentum form."""
        group = system.group
        sign = system.side.sign

        def residual(xi):
            return self.chart.dinverse(group, sign * xi).T @ system.legendre(xi / h) - m

        return residual

    def on_branch(self, system: AbstractLieSystem, m: Float[Array, " d"], h: Scalar, xi):
        """The branch rule: `ξ` is on the root branch continued from `h → 0`.

        Along that branch the residual's Jacobian `J(ξ)` starts at `∇²l/h` (determinant of
        the sign of `h^d`) and stays non-singular until the branch folds, where Newton stops
        converging; so a converged root whose `det J` has the other sign was reached across
        a fold — a root of (4.8) that no step continued from `h → 0` ends on (it can lie far
        inside the step bound: an anisotropic body at `h|Ω| = 0.56` was seen to converge
        to one). Such a root is reported as `RESULTS.step_too_large`, on both paths; and for
        the exp chart a root at a rotation angle of π or more (`ExpChart.beyond_branch`).
        """
        group = system.group
        J = jax.jacfwd(self.residual(system, m, h))(xi)
        # The sign from `slogdet`: `det J` itself, a product of `d` factors of the size
        # of `∇²l/h`, leaves float32's range for small inertias, long steps or large
        # algebras (SO(4), moments 1e-3, h = 1e5: 1.3e-44, computed as 0 in float32, and
        # a step on the branch was reported off it).
        sign, _ = jnp.linalg.slogdet(J)
        same_sign = sign * jnp.sign(h) ** group.algebra_dim > 0
        beyond = self.chart.beyond_branch(group.exp_norm(xi) ** 2, group.exp_radius)
        return same_sign & ~beyond

    def solve_increment(self, system: AbstractLieSystem, m: Float[Array, " d"], h: Scalar):
        """Solve the DEP equation for the increment coordinates `ξ_k` given `m_k`."""
        residual = self.residual(system, m, h)
        tolerance = newton_tolerance(jnp.max(jnp.abs(m)), m.dtype, self.rtol, self.atol)
        # Explicit-Euler guess `h·ξ(m)`: O(h²) from the root, so Newton needs few steps.
        return newton_solve(residual, h * system.velocity(m), tolerance, self.max_steps)

    def free_step(self, system: AbstractLieSystem, g, m, h: Scalar):
        # Where a kernel applies (the rigid body with principal moments, the free body on
        # SE(3)): the same root, closed forms throughout, and under `jax.vmap` the batched
        # kernel (`AbstractBatchKernel.one_body`: its form for one body).
        fast = self.kernel_step(system, g, m, h)
        if fast is not None:
            return fast
        group = system.group
        xi, info = self.solve_increment(system, m, h)
        F = self.chart.map(group, xi)
        # `compose`, not `@`: a group may keep its product on the group to round-off (SE(3)
        # re-orthonormalises the rotation block; the momentum of a symmetry relies on it).
        g_next = system.side.compose(group, g, F)
        m_next = system.side.momentum_after(group, F, m)

        result = jnp.where(info.converged, RESULTS.successful, RESULTS.newton_not_converged)
        on_branch = self.on_branch(system, m, h, jax.lax.stop_gradient(xi))
        result = jnp.where(on_branch, result, RESULTS.step_too_large)
        finite = jnp.isfinite(info.residual) & jnp.all(jnp.isfinite(m_next))
        result = jnp.where(finite, result, RESULTS.nonfinite)
        return g_next, m_next, StepInfo(result, info.iterations, info.residual)
