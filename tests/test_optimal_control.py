"""Optimal control through the forced variational integrator: rest-to-rest reorientation.

Problem: from rest at `g = I` to rest at `g_f = exp(θ_f a)` (θ_f = 150°) in fixed time
`T`, minimising `Σ_k h|u_k|²` over a held control sequence `u` (`lievi.Control`, body
torques), with a terminal attitude and momentum cost. The terminal cost is an augmented
Lagrangian, `λ·c + (ρ/2)|c|²` with `c = (log(g_fᵀ g_N), Π_N)`, minimised by `optax.lbfgs`
for fixed `λ`; then `λ ← λ + ρc` (the method of multipliers), so the terminal conditions
are met to round-off rather than to `O(1/ρ)`.

Closed form for a spherical body `J = jI`. Euler's equation is `jΩ̇ = u` (`Π × Ω = 0`),
so `∫|u|² = j²∫|Ω̇|²`: the rest-to-rest problem is the minimum-acceleration ("Riemannian
cubic") problem on SO(3) with its bi-invariant metric (Noakes, Heinzinger & Paden, IMA J.
Math. Control Inf. 6 (1989)). Restricted to rotations about the fixed axis `a`,
`θ(t)`, it is `min ∫ j²θ̈² dt` with `θ(0) = θ̇(0) = θ̇(T) = 0`, `θ(T) = θ_f`; its
Euler–Lagrange equation `θ'''' = 0` and the four boundary conditions give

    θ(t) = θ_f (3s² − 2s³),  s = t/T,   u(t) = jθ̈ a = (j θ_f / T²)(6 − 12s) a,
    J* = ∫|u|² dt = 12 j² θ_f² / T³.

That this eigenaxis manoeuvre is the optimum among all manoeuvres (not only those about a
fixed axis) is checked numerically: the discrete optimum, started from a random control
with components off the axis, comes out on the axis to round-off, and its cost converges
to `J*` at order 2. Along the axis the discrete problem is the continuous one with the
integrals replaced by midpoint sums (`θ_N = Σ h u_k (T − t_{k+½})` exactly), whose optimum
is again linear in time, `u_k = b (t_{k+½} − T/2)`; the midpoint rule's error on `∫(t − T/2)²`
gives `J_d/J* = 1/(1 − (h/T)²)`, i.e. `J_d/J* − 1 = 1/(N² − 1)` for `N` steps.
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu
import pytest

import lievi

THETA = 5 * np.pi / 6  # 150°
AXIS = jnp.array([1.0, 2.0, 2.0]) / 3
T = 2.0
PENALTY = 100.0  # ρ of the augmented Lagrangian
GRADIENT_TOLERANCE = 1e-11  # of each inner L-BFGS solve


def lbfgs(fun, x0, max_iter: int, tol: float):
    """Minimise `fun` from `x0` with `optax.lbfgs` in a `lax.while_loop` (jit-compatible)."""
    opt = optax.lbfgs(memory_size=20)
    value_and_grad = optax.value_and_grad_from_state(fun)

    def step(carry):
        x, state = carry
        value, grad = value_and_grad(x, state=state)
        updates, state = opt.update(grad, state, x, value=value, grad=grad, value_fn=fun)
        return optax.apply_updates(x, updates), state

    def keep_going(carry):
        _, state = carry
        count, grad = otu.tree_get(state, "count"), otu.tree_get(state, "grad")
        return (count == 0) | ((count < max_iter) & (otu.tree_norm(grad) >= tol))

    x, _ = jax.lax.while_loop(keep_going, step, (x0, opt.init(x0)))
    return x


def terminal_defect(system, integrator, u, h, g_target):
    """`c = (log(g_fᵀ g_N), Π_N)`: zero exactly at rest at the target."""
    n = u.shape[0]
    sol = lievi.simulate(
        system,
        integrator,
        jnp.eye(3),
        jnp.zeros(3),
        h=h,
        n_steps=n,
        save_every=n,
        forcing=lievi.Control(u),
        throw=False,
    )
    return jnp.concatenate([lievi.SO3.log(g_target.T @ sol.g[-1]), sol.m[-1]])


def reorient(system, g_target, n, *, integrator=lievi.DEP(), u0=None, max_outer=15, tol=1e-12):
    """The discrete optimal control `u` (n, 3) and the terminal defect it leaves."""
    h = T / n

    @jax.jit
    def inner(u, multiplier):
        def objective(u):
            c = terminal_defect(system, integrator, u, h, g_target)
            return h * jnp.sum(u**2) + multiplier @ c + PENALTY / 2 * c @ c

        u = lbfgs(objective, u, 3000, GRADIENT_TOLERANCE)
        return u, terminal_defect(system, integrator, u, h, g_target)

    u = jnp.zeros((n, 3)) if u0 is None else u0
    multiplier = jnp.zeros(6)
    for _ in range(max_outer):
        u, c = inner(u, multiplier)
        multiplier = multiplier + PENALTY * c
        if float(jnp.max(jnp.abs(c))) < tol:
            break
    return u, c


def closed_form_control(j, n):
    """`u(t)` of the spherical body at the step midpoints, (n, 3)."""
    s = (np.arange(n) + 0.5) / n
    return (j * THETA / T**2 * (6 - 12 * s))[:, None] * np.asarray(AXIS)


def sphere_errors(n, j=1.0):
    sphere = lievi.RigidBody(jnp.full(3, j))
    g_target = lievi.SO3.exp(THETA * AXIS)
    u0 = jnp.asarray(0.1 * np.random.default_rng(n).normal(size=(n, 3)))  # off the axis
    u, c = reorient(sphere, g_target, n, u0=u0)
    h = T / n
    cost = float(h * jnp.sum(u**2))
    optimum = 12 * j**2 * THETA**2 / T**3
    off_axis = float(jnp.max(jnp.abs(u - (u @ AXIS)[:, None] * AXIS)))
    profile = float(jnp.max(jnp.abs(u - closed_form_control(j, n)))) / (6 * j * THETA / T**2)
    return abs(cost - optimum) / optimum, profile, off_axis, float(jnp.max(jnp.abs(c)))


def test_sphere_discrete_optimum_is_the_eigenaxis_manoeuvre():
    """At a coarse step: on the eigenaxis to round-off, and `J_d/J* − 1 = 1/(N² − 1)`."""
    n = 16
    cost_error, profile_error, off_axis, defect = sphere_errors(n)
    assert defect < 1e-12
    assert off_axis < 1e-9
    assert abs(cost_error - 1 / (n**2 - 1)) < 1e-6 / n**2, cost_error
    assert profile_error < 1 / n**2, profile_error


@pytest.mark.slow
def test_sphere_discrete_optimum_converges_to_the_closed_form():
    ns = [16, 32, 64, 128]
    results = [sphere_errors(n) for n in ns]
    cost_errors = [r[0] for r in results]
    order = -np.polyfit(np.log(ns), np.log(cost_errors), 1)[0]
    assert abs(order - 2) < 0.05, (order, cost_errors)
    assert cost_errors[-1] <= 1e-4, cost_errors
    profile_errors = [r[1] for r in results]
    assert profile_errors[-1] <= 1e-4, profile_errors
    assert max(r[2] for r in results) < 1e-9  # eigenaxis
    assert max(r[3] for r in results) < 1e-12  # at rest at the target


@pytest.mark.slow
def test_asymmetric_spacecraft_reaches_the_target():
    craft = lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))
    g_target = lievi.SO3.exp(THETA * AXIS)
    n = 60
    u, c = reorient(craft, g_target, n)
    sol = lievi.simulate(
        craft, lievi.DEP(), jnp.eye(3), jnp.zeros(3), h=T / n, n_steps=n, forcing=lievi.Control(u)
    )
    attitude_error = float(jnp.linalg.norm(lievi.SO3.log(g_target.T @ sol.g[-1])))
    assert attitude_error <= 1e-6, attitude_error
    assert float(jnp.max(jnp.abs(sol.m[-1]))) <= 1e-6
    # The gyroscopic coupling moves the optimum off the eigenaxis (unlike the sphere's).
    off_axis = float(jnp.max(jnp.abs(u - (u @ AXIS)[:, None] * AXIS)))
    assert off_axis > 1e-2, off_axis
