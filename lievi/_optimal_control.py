"""`solve_optimal_control`: discrete optimal control through `simulate`.

The controls are a held sequence `u` (`lievi.Control`: one generalised force per step,
entering the step through the discrete Lagrange–d'Alembert principle), the cost is
`Σ_k h|u_k|²`, and the terminal conditions `c = (log(g_f⁻¹ g_N), m_N − m_f) = 0` are
imposed by an augmented Lagrangian `λ·c + (ρ/2)|c|²`: for fixed `λ` it is minimised by
`optax.lbfgs` in a `lax.while_loop`, with exact gradients through `lievi.simulate`; then
`λ ← λ + ρc` (the method of multipliers), so the conditions are met to round-off rather
than to `O(1/ρ)`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu
from jaxtyping import Array, Float

from ._forcing import Control
from ._save import Save
from ._simulate import simulate
from ._solution import Solution


class OptimalControlSolution(eqx.Module):
    """The result of `lievi.solve_optimal_control`.

    **Attributes:**

    - `controls`: the optimal control sequence `u`, shape `(n_steps, *momentum_shape)`:
      `(n_steps, d)` for one body, `(n_steps, N, d)` for a system of `N` bodies (one
      generalised force per body and step, as `lievi.Control` takes it).
    - `solution`: the trajectory it drives (`lievi.simulate` with `forcing=Control(u)`,
      every step saved, `throw=False`: read `solution.result`).
    - `converged`: whether `constraint_violation ≤ tol`.
    - `iterations`: multiplier updates (outer iterations) taken.
    - `inner_iterations`: L-BFGS iterations, summed over the outer iterations.
    - `constraint_violation`: `max|c|` at the end, `c` the terminal defect.
    - `cost`: `Σ_k h|u_k|²`.
    - `multipliers`: the final Lagrange multipliers `λ` of the terminal conditions.
    """

    controls: Float[Array, "n_steps ..."]
    solution: Solution
    converged: bool
    iterations: int
    inner_iterations: int
    constraint_violation: float
    cost: float
    multipliers: Float[Array, " c"]


class _Problem(eqx.Module):
    """The data of one problem (traced by the compiled inner solve)."""

    system: eqx.Module
    integrator: eqx.Module
    g0: Array
    m0: Array
    g_target: Array
    m_target: Array | None
    h: Array

    def defect(self, u):
        """The terminal defect `c`: zero exactly at the target."""
        n = u.shape[0]
        sol = simulate(
            self.system,
            self.integrator,
            self.g0,
            self.m0,
            h=self.h,
            n_steps=n,
            save=Save(g=True, m=True, stats=False, every=n),
            forcing=Control(u),
            throw=False,
        )
        group = self.system.group
        # One defect per body where the system has several: raveled into one vector.
        c = [group.log(group.compose(group.inverse(self.g_target), sol.g[-1])).ravel()]
        if self.m_target is not None:
            c.append((sol.m[-1] - self.m_target).ravel())
        return jnp.concatenate(c)

    def cost(self, u):
        return self.h * jnp.sum(u**2)


def _lbfgs(fun, x0, max_iter: int, tol, memory_size: int):
    """Minimise `fun` from `x0` with `optax.lbfgs` in a `lax.while_loop`; stops when the
    gradient norm is below `tol` or after `max_iter` iterations. Returns `(x, iterations)`."""
    opt = optax.lbfgs(memory_size=memory_size)
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

    x, state = jax.lax.while_loop(keep_going, step, (x0, opt.init(x0)))
    return x, otu.tree_get(state, "count")


@eqx.filter_jit
def _inner_solve(problem: _Problem, u, multiplier, penalty, tol, max_iter: int, memory: int):
    """One augmented-Lagrangian subproblem: `u`, its defect, and the L-BFGS iterations."""

    def objective(u):
        c = problem.defect(u)
        return problem.cost(u) + multiplier @ c + penalty / 2 * c @ c

    u, iterations = _lbfgs(objective, u, max_iter, tol, memory)
    return u, problem.defect(u), iterations


def solve_optimal_control(
    system,
    integrator,
    g0: Float[Array, "*element"],
    m0: Float[Array, "*momentum"],
    target,
    n_steps: int,
    h,
    *,
    u0: Float[Array, "n_steps ..."] | None = None,
    penalty: float = 100.0,
    tol: float = 1e-12,
    max_iterations: int = 15,
    max_inner_iterations: int = 3000,
    gradient_tol: float = 1e-11,
    memory_size: int = 20,
) -> OptimalControlSolution:
    """The control sequence of least effort `Σ_k h|u_k|²` that takes `system` from
    `(g0, m0)` to `target` in `n_steps` steps of `integrator`.

    The control `u_k` is held over step `k` (`lievi.Control(u)`: for a rigid body, the
    body torque). The terminal conditions `c = (log(g_f⁻¹ g_N), m_N − m_f) = 0` are imposed
    by an augmented Lagrangian `λ·c + (ρ/2)|c|²`, minimised over `u` by `optax.lbfgs`
    with exact gradients through `lievi.simulate`, followed by the multiplier update
    `λ ← λ + ρc`, until `max|c| ≤ tol` (the method of multipliers: the conditions are met
    to round-off, not to `O(1/ρ)`). Each subproblem is one compiled call.

    **Arguments:**

    - `system`, `integrator`: as for `lievi.simulate`; the integrator must take a force
      (`lievi.AbstractKickIntegrator`, e.g. `lievi.DEP()`).
    - `g0`, `m0`: the initial state (momentum in algebra coordinates), of the system's
      `element_shape()` and `momentum_shape()`: `(n, n)` and `(d,)` for one body, one
      row per body for a system of several (`lievi.RigidBodies`: `(N, 4, 4)`, `(N, 6)`).
    - `target`: `(g_f, m_f)`, the terminal configuration and momentum (`m_f = 0`: arrive
      at rest), or `(g_f, None)` for a free terminal momentum; shaped as `g0`, `m0`.
    - `n_steps`: the number of steps (and of controls), a Python `int ≥ 1`.
    - `h`: the step size; the horizon is `T = n_steps · h`.
    - `u0`: the initial guess, shape `(n_steps, *momentum_shape)` (`(n_steps, d)` for one
      body, `(n_steps, N, d)` for `N` bodies, as `lievi.Control` takes it); zeros by
      default.
    - `penalty`: `ρ` of the augmented Lagrangian.
    - `tol`: the terminal-defect tolerance `max|c|` that ends the outer loop.
    - `max_iterations`: the most multiplier updates.
    - `max_inner_iterations`, `gradient_tol`, `memory_size`: of each L-BFGS subproblem
      (it stops when the gradient norm falls below `gradient_tol`).

    **Returns:** an `OptimalControlSolution`: the controls, the trajectory they drive, and
    the convergence report (`converged`, `iterations`, `constraint_violation`, `cost`).
    Not converging is reported there, not raised.
    """
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise ValueError(f"`n_steps` must be an integer ≥ 1, got {n_steps!r}.")
    if not (isinstance(target, tuple) and len(target) == 2):
        raise ValueError(
            "`target` must be a pair `(g_f, m_f)` (`m_f = None`: a free final momentum)."
        )
    for name, value in (("max_iterations", max_iterations), ("memory_size", memory_size)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"`{name}` must be an integer ≥ 1, got {value!r}.")
    g_target, m_target = target
    system.check_element("g0", g0)
    system.check_momentum("m0", m0)
    system.check_element("target[0]", g_target)
    if m_target is not None:
        system.check_momentum("target[1]", m_target)
    # One generalised force per step and body: the shape `lievi.Control` takes.
    shape = (n_steps, *system.momentum_shape())
    dtype = jnp.result_type(g0, m0, h, float)
    if u0 is None:
        u0 = jnp.zeros(shape, dtype)
    u = jnp.asarray(u0, dtype)
    if u.shape != shape:
        raise ValueError(
            f"`u0` must have shape (n_steps, *momentum_shape) = {shape} (one generalised "
            f"force per step{', a row per body' if len(shape) > 2 else ''}), got {u.shape}."
        )
    problem = _Problem(
        system,
        integrator,
        jnp.asarray(g0, dtype),
        jnp.asarray(m0, dtype),
        jnp.asarray(g_target, dtype),
        None if m_target is None else jnp.asarray(m_target, dtype),
        jnp.asarray(h, dtype),
    )
    size = int(np.prod(system.momentum_shape()))  # the defect's length per condition
    multiplier = jnp.zeros(size if m_target is None else 2 * size, dtype)
    penalty_, gradient_tol_ = jnp.asarray(penalty, dtype), jnp.asarray(gradient_tol, dtype)
    outer = inner = 0
    violation = float("nan")
    for outer in range(1, max_iterations + 1):
        u, c, iterations = _inner_solve(
            problem, u, multiplier, penalty_, gradient_tol_, max_inner_iterations, memory_size
        )
        inner += int(iterations)
        multiplier = multiplier + penalty * c
        violation = float(jnp.max(jnp.abs(c)))
        if violation <= tol or not np.isfinite(violation):
            break
    solution = simulate(
        system,
        integrator,
        problem.g0,
        problem.m0,
        h=problem.h,
        n_steps=n_steps,
        forcing=Control(u),
        throw=False,
    )
    return OptimalControlSolution(
        controls=u,
        solution=solution,
        converged=bool(violation <= tol),
        iterations=outer,
        inner_iterations=inner,
        constraint_violation=violation,
        cost=float(problem.cost(u)),
        multipliers=multiplier,
    )
