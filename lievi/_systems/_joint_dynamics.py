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
iteration `C M⁻¹ Cᵀ δ = −Φ(g)` (three iterations from a defect `O(h^{p+1})`: round-off),
and the momenta onto `C(g) ξ = 0` (`ArticulatedBodies.project_momentum`). The projection
moves the state by `O(h^{p+1})`, so the method keeps its order `p`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._groups._se3 import SE3
from ._tree_solve import block_tree_solver

# Simplified Newton iterations of the position projection, from a defect of the size of
# the method's local error: the first is Newton's, the others reuse its factorisation and
# contract less. From 1e-6 of `ℓ` (`RKMK8`, h = 0.08, the 5-link hinge chain of the docs)
# two left 2e-12, three round-off.
POSITION_ITERATIONS = 3
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
    joints hold to round-off afterwards, 64 ulps of the link length and of the positions
    (a step too long for the projection's iteration leaves them apart: the run reports
    it)."""
    rows = system.constraint_rows(g)
    solve = gram_solver(system, rows, m.dtype)
    for _ in range(POSITION_ITERATIONS):
        delta = solve(-system.constraints(g))
        g = jnp.einsum("nij,njk->nik", g, SE3.exp(system.velocity(rows.transpose_apply(delta))))
    m, _ = project(system, system.constraint_rows(g), m)
    size = 1 + jnp.max(jnp.abs(g[:, :3, 3])) / system.length_scale()
    held = system.joint_defect(g) <= HELD_ULPS * jnp.finfo(m.dtype).eps * size
    return g, m, held
