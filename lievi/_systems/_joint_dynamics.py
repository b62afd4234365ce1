"""The joints of `lievi.ArticulatedBodies` as the continuous equations see them: the
reaction that keeps the bodies' accelerations on the joints, and the projection of a
state back onto them. With these an explicit method (the Runge–Kutta–Munthe-Kaas methods,
`lievi.RKMK4` … `lievi.RKMK8`) integrates a tree of bodies — a *projection method*
(Hairer–Lubich–Wanner, *Geometric Numerical Integration*, §IV.4), not a variational one.

**The reaction (index reduction).** The equations of motion of the bodies on the joints
`Φ(g) = 0` are each body's Euler–Poincaré equation with the reaction `C(g)ᵀλ` added,

    ṁ = ad_ξᵀ m + M(g) + f + C(g)ᵀ λ,        ξ = M⁻¹ m,

(`C` the joints' Jacobian along the left-trivialised directions, `M` the bodies' kinetic
tensors), with `λ` whatever keeps `Φ(g(t)) = 0`. Differentiating `Φ` twice along the
motion, `C(g) ξ̇ + Ċ ξ = 0` (`Ċ` the derivative of `C(g(t))` along `ġ = g ξ̂`), gives `λ`
from the Gram matrix of the joints in the kinetic metric:

    C M⁻¹ Cᵀ λ = −(C M⁻¹ (ad_ξᵀ m + M(g) + f) + Ċ ξ).

The Gram matrix is factored by the joints' tree (`_tree_solve.py`), `Ċ ξ` is the
forward-mode derivative of the closed-form rows.

**The projection.** The index-reduced equations hold the joints only to the method's
local error, which drifts. After each step the poses are moved back onto `Φ = 0` along
the kinetic metric, `g_i ← g_i exp(M_i⁻¹ (Cᵀδ)_i)` with `δ` from the simplified Newton
iteration `C M⁻¹ Cᵀ δ = −Φ(g)` to round-off (two iterations from a defect of 1e-6 of `ℓ`),
and the momenta onto `C(g) ξ = 0` (`ArticulatedBodies.project_momentum`). The projection
moves the state by `O(h^{p+1})`, so the method keeps its order `p`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._groups._se3 import SE3
from .._newton import newton_solve
from ._tree_solve import block_tree_solver

# The position projection's iterations at most (simplified Newton, converging linearly
# at the rate of the defect: from 1e-6 of `ℓ` two, from 2e-3 — `RKMK8`, h = 0.08, a
# triple pendulum's fast swing — five); beyond them the step reports the joints apart.
POSITION_MAX_STEPS = 16
# The joints hold when their defect is within this many ulps of the link length and of
# the positions it is computed from (`x_p + R_p a_p − x_c − R_c a_c` rounds to the size
# of `x`): the implicit steps' default tolerance, 64 ulps.
HELD_ULPS = 64


def gram_solver(system, rows, dtype):
    """`r ↦ (C M⁻¹ Cᵀ)⁻¹ r` for the joints' rows `rows` (`JointRows`), factored once by the
    joints' tree: the kinetic-metric Gram matrix of the velocity projection, the
    reaction and the position projection."""
    n = system.n_bodies
    # `M⁻¹` per body `(N, 6, 6)`, column `k` the velocity of the momentum `e_k`.
    basis = jnp.eye(6, dtype=dtype)
    M_inv = jnp.stack([system.velocity(jnp.broadcast_to(e, (n, 6))) for e in basis], axis=-1)
    structure = system.joint_structure()
    return block_tree_solver(rows.gram_blocks(M_inv, rows, structure), structure)


def project(system, rows, m):
    """`(m + Cᵀμ, μ)` with `C M⁻¹ (m + Cᵀμ) = 0` (the kinetic-metric projection), with one
    step of iterative refinement so that the velocity constraints hold to round-off."""
    solve = gram_solver(system, rows, m.dtype)
    impulse = jnp.zeros((rows.n_rows,), m.dtype)
    for _ in range(2):
        step = -solve(rows.apply(system.velocity(m)))
        m = m + rows.transpose_apply(step)
        impulse = impulse + step
    return m, impulse


def constrained_rate(system, g, m, m_dot):
    """`ṁ + Cᵀλ`: the bodies' rate `m_dot` (`(N, 6)`, every force but the joints') with the
    reaction that keeps their accelerations on the joints (module docstring)."""
    xi = system.velocity(m)
    rows = system.constraint_rows(g)
    # `Ċ ξ`: the rows' derivative along the motion `ġ = g ξ̂`, applied to `ξ`.
    along = jnp.einsum("nij,njk->nik", g, SE3.hat(xi))
    bias = jax.jvp(lambda p: system.constraint_rows(p).apply(xi), (g,), (along,))[1]
    solve = gram_solver(system, rows, m.dtype)
    reaction = solve(-(rows.apply(system.velocity(m_dot)) + bias))
    return m_dot + rows.transpose_apply(reaction)


def project_state(system, g, m):
    """`(g, m, held)`: the poses moved onto the joints along the kinetic metric and the
    momenta onto their velocity constraints (module docstring); `held` is whether the
    position iteration brought the joints to round-off, 64 ulps of the link length and of
    the positions, within `POSITION_MAX_STEPS` (a step too long leaves them apart: the run
    reports it). Differentiated by the implicit function theorem at the root, as the
    implicit steps are (`newton_solve`)."""
    rows = system.constraint_rows(g)
    solve = gram_solver(system, rows, m.dtype)
    length = system.length_scale().astype(m.dtype)

    def moved(delta):
        return jnp.einsum("nij,njk->nik", g, SE3.exp(system.velocity(rows.transpose_apply(delta))))

    def defect(delta):
        return system.constraints(moved(delta)) / length

    size = jax.lax.stop_gradient(1 + jnp.max(jnp.abs(g[:, :3, 3])) / length)
    tolerance = HELD_ULPS * jnp.finfo(m.dtype).eps * size
    delta, info = newton_solve(
        defect,
        jnp.zeros((rows.n_rows,), m.dtype),
        tolerance,
        POSITION_MAX_STEPS,
        approximate_solve=lambda r: solve(length * r),
    )
    g = moved(delta)
    m, _ = project(system, system.constraint_rows(g), m)
    return g, m, info.converged
