"""RATTLE on SE(3)ᴺ: the DEP step of each body with holonomic joint constraints.

The constrained discrete Lagrangian of `lievi.ArticulatedBodies` is the free bodies' DEP
discrete Lagrangian (paper §4, (4.7), on SE(3), with the chart `φ`) with the trapezoidal
potential (§7), restricted to the joints' constraint manifold `Φ(g) = 0`:

    L_d(g_k, g_{k+1}) = Σ_i h l_i(φ⁻¹(g_{k,i}⁻¹ g_{k+1,i})/h) − (h/2)(V(g_k) + V(g_{k+1})).

Its discrete Euler–Lagrange equations with multipliers, written in momentum form with the
velocity constraint imposed on the momenta (the RATTLE form; Hairer–Lubich–Wanner,
*Geometric Numerical Integration*, §VII.1.4; on Lie groups, Leyendecker–Marsden–Ortiz and
Kol–Laird–Leimkuhler), are, with `M` the potential's force, `C` the constraint Jacobian
along the left-trivialised directions and `M_i` each body's kinetic tensor:

    m_k⁺ = m_k + (h/2) M(g_k) + C(g_k)ᵀ Λ_k,                         (kick + reaction)
    m_{k,i}⁺ = dφ⁻¹(ξ_i)ᵀ M_i ξ_i / h,   g_{k+1,i} = g_{k,i} φ(ξ_i),   (each body's DEP)
    Φ(g_{k+1}) = 0,                                                  (position level)
    m_{k+1} = Ad_{φ(ξ)}ᵀ m_k⁺ + (h/2) M(g_{k+1}) + C(g_{k+1})ᵀ μ_k,   (DLP + kick + reaction)
    C(g_{k+1}) M⁻¹ m_{k+1} = 0.                                      (velocity level)

The first three are one nonlinear system for the increments `ξ` `(N, 6)` and the
reaction impulses `Λ_k` `(c,)`, solved by a simplified Newton iteration on the
Jacobian's block structure, approximated once per step (`_rattle_schur.py`), or by Newton's
method (`full_newton=True`) — both through `_newton.py`: implicit differentiation with
the exact Jacobian at the root, `RESULTS.newton_not_converged` otherwise; the last two
are a linear solve for `μ_k`. The map is symmetric (its adjoint, the same equations with
`−h` read backwards, is itself: `Λ_k ↔ −μ_k`), symplectic on the constraint manifold's
cotangent bundle and second order, so `lievi.Composition` raises its order. The momentum
of a symmetry of `L_d` and of the joints — the total linear and angular momentum of a
floating base, the vertical angular momentum about the pivot of a fixed base in gravity —
is conserved exactly (discrete Noether theorem): each DEP step keeps its body's spatial
momentum whatever its root's accuracy, and the reactions are internal forces.

An external force `f` (`lievi.Control`, `lievi.ForceLaw`) adds the discrete
Lagrange–d'Alembert kicks `(h/2) f(t_k, g_k, m_k)` to the first line and
`(h/2) f(t_{k+1}, g_{k+1}, m_{k+1})` to the fourth (implicit in `m_{k+1}` when `f` depends
on the momentum: solved before the projection, as the kick methods solve it).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Scalar

from .._checks import as_int
from .._groups._charts import AbstractChart, as_chart
from .._groups._se3 import SE3
from .._newton import check_newton_options, newton_solve, newton_tolerance
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from ._base import AbstractIntegrator, StepInfo, checked_force, forced_end_kick
from ._rattle_blocks import momentum_blocks
from ._rattle_schur import kkt_solver


def _constrained(system):
    """`system` if it has joints (`constraint_jacobian`), else a `ValueError`."""
    if not hasattr(system, "constraint_jacobian"):
        raise ValueError(
            f"RATTLE steps systems with joints (lievi.ArticulatedBodies), got "
            f"{type(system).__name__}; for free bodies use lievi.DEP."
        )
    return system


class RATTLE(AbstractIntegrator):
    """The RATTLE method on SE(3)ᴺ for `lievi.ArticulatedBodies`: each body's DEP step
    with the joints enforced by discrete Lagrange multipliers, at position and at velocity
    level. Second order, symmetric (so `lievi.Composition` raises the order), symplectic
    and momentum-preserving on the joints' constraint manifold.

    **Arguments:**

    - `chart`: `"exp"` (default) or `"cayley"`, as for `lievi.DEP`.
    - `rtol`, `atol`: the iteration stops when every body's momentum equation holds to
      `atol + rtol·‖m‖_∞` (`‖m‖_∞` floored at `ε‖M‖ℓ/h`, the momentum of a motion of one ulp of
      the chain a step, so that a chain at rest has a scale) and every joint to
      `(atol + rtol)·ℓ` (`ℓ` the link length).
      Default: `rtol` = 64 ulps of the dtype, `atol` = 0.
    - `max_steps`: maximum iterations per step; exceeding it is reported as
      `RESULTS.newton_not_converged`.
    - `full_newton`: `False` (default) iterates with the Jacobian built once per step,
      at the guess (each body's 6×6 block, the joints' rows in closed form to first
      order) and factored by its structure (the joints' Schur
      complement): a simplified Newton iteration, cheap per step and per iteration.
      `True` runs Newton's method with the whole Jacobian rebuilt by `jax.jacfwd` at
      every iteration (the same root, several times the cost). The derivatives are the
      same either way (implicit differentiation with the exact Jacobian at the root).
    """

    chart: AbstractChart = eqx.field(default="exp", static=True, converter=as_chart)
    rtol: float | None = eqx.field(default=None, static=True)
    atol: float | None = eqx.field(default=None, static=True)
    max_steps: int = eqx.field(default=20, static=True, converter=as_int)
    full_newton: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        check_newton_options(self.max_steps, self.rtol, self.atol)

    def order(self) -> int:
        return 2

    def is_symmetric(self) -> bool:
        return True

    def own_step(self) -> bool:
        return type(self) is RATTLE

    def step(self, system: AbstractLieSystem, g, m, h: Scalar, force=None, t: Scalar = 0.0):
        return self._rattle_step(system, g, m, h, None, force, t)[:3]

    def _start_cache(self, system: AbstractLieSystem, g):
        """What a step takes over from the one before, all of `g_k` alone: the joints'
        reaction force `(c,)` its impulse starts from (none known at the start of a run:
        zero, the explicit guess of `step`), the joints' rows `C(g_k)` and the potential's
        force `M(g_k)` (`None` without one), which the step before built at its end for
        its projection and its end kick."""
        system = _constrained(system)
        g = g.astype(jnp.result_type(g, float))
        reaction = jnp.zeros((system.n_constraints,), g.dtype)
        return reaction, system.constraint_rows(g), _potential_force(system, g)

    def _step_from_cache(self, system, g, m, h, cache, force, t):
        return self._rattle_step(system, g, m, h, cache, force, t)

    def _rattle_step(self, system, g, m, h, cache, force, t):
        """The step from `cache` (`_start_cache`'s `(reaction, C(g_k), M(g_k))` of the
        step before, or `None`: computed here, the reaction guessed zero), returning the
        cache of the next step after `(g_{k+1}, m_{k+1}, info)`: the reaction of its
        velocity projection, `2μ_k/h`, and the rows and force at `g_{k+1}`, which the
        projection and the end kick built (each was built twice a step before).

        The start impulse `Λ_{k+1}` and the end impulse `μ_k` of the step before are both
        `(h/2) λ(t_{k+1}) + O(h²)`: guessed from `μ_k`, the iteration starts about `h|ω|`
        (relative) from the reaction instead of a whole reaction away, and takes one
        iteration fewer on the chains of docs/articulated.md. The guess moves the iterates,
        not the root (every iteration evaluates the exact residual) nor its derivative
        (implicit, at the root; the guess carries none). As a force, not an impulse, it
        carries over between steps of different `h` (`lievi.Composition`'s stages)."""
        system = _constrained(system)
        n = system.n_bodies
        tensor = system.tensor.astype(m.dtype)
        if cache is None:
            reaction = None
            C0, start_force = system.constraint_rows(g.astype(m.dtype)), _potential_force(system, g)
        else:
            reaction, C0, start_force = cache
        start = m
        if start_force is not None:
            start = start + h / 2 * start_force
        if force is not None:
            # The discrete Lagrange–d'Alembert force at g_k: f_k⁻ = (h/2) f(t_k, g_k, m_k).
            start = start + h / 2 * checked_force(force, t, g, m)
        c = system.n_constraints
        length = system.length_scale().astype(m.dtype)
        # The momentum equations relative to the size of the momenta, the joints to `ℓ`:
        # one tolerance then means "to 64 ulps" for both. The scale does not move the
        # root, so it carries no derivative. From rest it is floored at the momentum of a
        # motion of one ulp of the chain's size a step, `ε·‖M‖·ℓ/h`: floored at `tiny`
        # instead, the momentum rows of the Jacobian, `(M/h)/tiny`, overflowed and the
        # implicit derivative of a run started from rest was NaN.
        floor = jnp.finfo(m.dtype).eps * jnp.max(jnp.abs(tensor)) * length / jnp.abs(h)
        scale = jax.lax.stop_gradient(jnp.maximum(jnp.max(jnp.abs(start)), floor))

        def unpack(z):
            return z[: 6 * n].reshape(n, 6), z[6 * n :]

        def advanced(xi):
            F = self.chart.map(SE3, xi)
            return SE3.compose(g, F), F

        def momentum_term(xi, M):
            """`dφ⁻¹(ξ_i)ᵀ M_i ξ_i / h`, body `i`'s side of its momentum equation."""
            return self.chart.dinverse_transpose_apply(SE3, xi, M @ xi) / h

        def joints_after(xi):
            return system.constraints(advanced(xi)[0])

        def residual(z):
            xi, impulse = unpack(z)
            m_plus = start + C0.transpose_apply(impulse)
            momentum = jax.vmap(momentum_term)(xi, tensor) - m_plus
            return jnp.concatenate([momentum.reshape(-1) / scale, joints_after(xi) / length])

        # Explicit-Euler guess with the reaction guessed: O(h²) from the root, or O(h³)
        # with the last step's reaction.
        impulse0 = jnp.zeros((c,), m.dtype)
        if reaction is not None:
            impulse0 = jnp.where(jnp.isfinite(reaction), h / 2 * reaction, 0).astype(m.dtype)
        xi0 = h * system.velocity(start + C0.transpose_apply(impulse0))
        guess = jnp.concatenate([xi0.reshape(-1), impulse0])
        tolerance = newton_tolerance(1.0, m.dtype, self.rtol, self.atol)
        if self.full_newton:
            z, info = newton_solve(residual, guess, tolerance, self.max_steps)
        else:
            # The Jacobian at the guess (O(h²) from the root): each body's 6×6 momentum
            # block in closed form to O(|ξ₀|²) (`_rattle_blocks.py`), and the joints' rows
            # `C(g φ(ξ₀)) (1 − ½ ad_ξ₀)` per body, `∂Φ(g φ(ξ))/∂ξ` to O(|ξ₀|²), with `C` in
            # closed form: `jacfwd` of the joints (6N directions through the chart) was the
            # largest part of a batched step. The constant block `M_i/h` (exact to O(|ξ|))
            # was tried too: it stalled a floating chain under joint torques at h = 0.01
            # (`test_joint_torque_keeps_total_momentum_of_floating_chain`).
            blocks = momentum_blocks(xi0, tensor, h, self.chart.ad_squared)
            C1 = system.constraint_rows(advanced(xi0)[0])
            rows = C1.times_blocks(jnp.eye(6, dtype=m.dtype) - 0.5 * jax.vmap(SE3.ad)(xi0))
            solve = kkt_solver(blocks, rows, C0, scale, length, system.joint_structure())
            z, info = newton_solve(
                residual, guess, tolerance, self.max_steps, approximate_solve=solve
            )
        xi, impulse = unpack(z)
        m_plus = start + C0.transpose_apply(impulse)
        g_next, F = advanced(xi)
        m_next = jnp.einsum("nji,nj->ni", jax.vmap(SE3.Ad)(F), m_plus)
        end_force = _potential_force(system, g_next)
        if end_force is not None:
            m_next = m_next + h / 2 * end_force
        iterations, residual_norm = info.iterations, info.residual
        result = jnp.where(info.converged, RESULTS.successful, RESULTS.newton_not_converged)
        if force is not None:
            m_next, kick = forced_end_kick(
                force, t + h, g_next, m_next, h, result, self.rtol, self.atol
            )
            iterations = iterations + kick.iterations
            residual_norm = jnp.maximum(residual_norm, kick.residual)
            result = RESULTS.first_failure(result, kick.result)
        C_next = system.constraint_rows(g_next)
        m_next, end_impulse = system.project_with_impulse(g_next, m_next, C_next)
        finite = jnp.isfinite(residual_norm) & jnp.all(jnp.isfinite(m_next))
        # A residual that turned non-finite from finite data is the iteration diverging
        # (a step too long for it), which is `newton_not_converged` as when it stalls; the
        # root is then the finite guess (`newton_solve`). Non-finite data is `nonfinite`.
        diverged = ~info.converged & jnp.all(jnp.isfinite(start)) & jnp.all(jnp.isfinite(m_next))
        result = jnp.where(finite | diverged, result, RESULTS.nonfinite)
        info = StepInfo(result.astype(jnp.int32), iterations, residual_norm)
        return g_next, m_next, info, (2 * end_impulse / h, C_next, end_force)


def _potential_force(system, g):
    """The potential's force `M(g)` `(N, 6)`, or `None` without a potential."""
    return None if system.potential is None else system.force(g)
