"""Newton's method inside `jax.lax.while_loop`, differentiated implicitly.

The root is differentiated by the implicit function theorem: its derivative with respect
to anything the residual closes over (momentum, inertia, h) is `dx = −J⁻¹ ∂r` at the
converged root, not the derivative of the iterations, so reverse mode works (it cannot go
through a `while_loop`) and the derivative does not depend on how many iterations were
taken. It is a `jax.custom_jvp`, traced only when differentiated, as the kernels' roots
are (`lievi._kernels._implicit`): `jax.lax.custom_root` linearised the residual and traced
its Jacobian whenever the step was traced, forward runs included.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, Float, Int, Scalar

# The name (`jax.ad_checkpoint.checkpoint_name`) of each implicit step's root: a
# `jax.checkpoint` that keeps it stores the root, and the backward pass evaluates the
# implicit derivative there instead of solving again (`simulate`, `simulate_batch`).
ROOT_NAME = "lievi_step_root"


def check_newton_options(max_steps, rtol, atol) -> None:
    """Raise a `ValueError` naming the option when a Newton integrator's `max_steps`,
    `rtol` or `atol` is unusable (called from the integrators' `__check_init__`)."""
    # Any integer type (NumPy's too, as `n_steps` accepts), not bool.
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive integer, got {max_steps!r}.")
    for name, value in (("rtol", rtol), ("atol", atol)):
        if value is not None and not value >= 0:
            raise ValueError(f"`{name}` must be ≥ 0, got {value!r}.")


def newton_tolerance(scale, dtype, rtol: float | None = None, atol: float | None = None):
    """The stopping tolerance of every implicit step: `atol + rtol·scale`, relative by default.

    `scale` is the size of the terms of the equation (for the DEP and Moser–Veselov
    equations in momentum form: `‖m‖_∞`, which the Legendre term matches at the root).
    The default is *relative*: `rtol` = 64 ulps of `dtype`, `atol` = 0, so the test — and
    hence the computed step — is invariant under a change of units, `(I, m) → (cI, cm)`
    and `(h, m) → (h/c, cm)`, for every `c`. An absolute default would let the
    explicit-Euler guess "converge" with no iteration for a body in small units.
    The floor is the smallest normal number of `dtype`: for `m = 0` the guess `ξ = 0` is
    the exact root (residual exactly 0), and for `m ≠ 0` the residual of the guess is
    not below it unless `m` itself is at the underflow threshold.

    The same function sets the tolerance of the batched fast path, so both entry points
    stop on the same test.
    """
    eps_tol = 64 * float(jnp.finfo(dtype).eps)
    rtol = eps_tol if rtol is None else rtol
    atol = 0.0 if atol is None else atol
    floor = float(jnp.finfo(dtype).tiny)
    return jnp.maximum(atol + rtol * scale, floor)


class NewtonInfo(eqx.Module):
    """What a Newton solve did: iterations taken, final residual ∞-norm, convergence."""

    iterations: Int[Array, ""]
    residual: Float[Array, ""]
    converged: Array


def _jacobian_and_value(residual, x):
    """`(∂r/∂x, r(x))` from one forward-mode pass (the value rides along as aux)."""

    def value_twice(y):
        r = residual(y)
        return r, r

    return jax.jacfwd(value_twice, has_aux=True)(x)


def _cramer3(J, r):
    """`J⁻¹ r` for a 3×3 `J` by Cramer's rule: elementwise, so it vectorises under `vmap`
    (a batched `linalg.solve` of 3×3 systems does not, on CPU)."""
    adjugate = jnp.stack(
        [jnp.cross(J[1], J[2]), jnp.cross(J[2], J[0]), jnp.cross(J[0], J[1])], axis=-1
    )
    return adjugate @ r / jnp.dot(J[0], adjugate[:, 0])


def newton_solve(
    residual: Callable[[Float[Array, " d"]], Float[Array, " d"]],
    x0: Float[Array, " d"],
    tolerance: Scalar,
    max_steps: int,
    residual_and_jacobian: Callable | None = None,
    approximate_solve: Callable | None = None,
) -> tuple[Float[Array, " d"], NewtonInfo]:
    """Find `x` with `residual(x) = 0` starting from `x0`.

    Stops when `‖residual(x)‖_∞ ≤ tolerance`, on a non-finite residual, or after
    `max_steps` iterations; `NewtonInfo.converged` says which. `residual_and_jacobian`, if
    given, is `x ↦ (r(x), ∂r/∂x)` in closed form (e.g. `AbstractLieSystem.closed_form_residual`)
    and replaces `residual` and its `jax.jacfwd` Jacobian; a 3×3 system is then solved by
    Cramer's rule, in the solve and in the implicit derivative.

    `approximate_solve`, if given, is `r ↦ J̃⁻¹ r` with `J̃` an approximation of the Jacobian
    (e.g. one factored once, by its structure): the iterations are then the simplified
    Newton iteration `x ← x − J̃⁻¹ r(x)`, one residual evaluation each and no Jacobian.
    It converges to the same root (linearly, as fast as `J̃` is close to `J`); the implicit
    derivative at the root still uses the exact Jacobian, so derivatives do not depend on
    `J̃`.
    """
    # The residual (and its Jacobian in closed form, where given) with what it closes over
    # as arguments, traced once: the iterations run on those cut from the gradient, and
    # `_at_root` adds the implicit derivative with respect to them.
    linear_solve = jnp.linalg.solve
    if residual_and_jacobian is None:
        value, consts = jax.closure_convert(residual, x0)
        jacobian = jax.jacfwd(value)
    else:
        both, consts = jax.closure_convert(residual_and_jacobian, x0)
        value, jacobian = (functools.partial(_part, both, i) for i in (0, 1))
        if jnp.shape(x0) == (3,):
            linear_solve = _cramer3
    cut = jax.lax.stop_gradient(consts)

    def iterate(evaluate, step, guess):
        def cond(carry):
            _, r, _, it = carry
            norm = jnp.max(jnp.abs(r))
            return (norm > tolerance) & jnp.isfinite(norm) & (it < max_steps)

        def body(carry):
            x, r, jac, it = carry
            x = x - step(jac, r)
            jac, r = evaluate(x)
            return x, r, jac, it + 1

        jac, r = evaluate(guess)
        x, r, _, it = jax.lax.while_loop(cond, body, (guess, r, jac, jnp.array(0, jnp.int32)))
        # A diverged solve (reported through the residual) hands back the finite guess:
        # the implicit derivative is then evaluated at a finite point, so a failed step
        # whose output is masked contributes 0, not NaN, to a gradient.
        x = jnp.where(jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(r)), x, guess)
        return x, it, jnp.max(jnp.abs(r))

    guess = jax.lax.stop_gradient(x0)
    if approximate_solve is not None:
        # No Jacobian in the loop (its slot carries nothing); the approximate solve's
        # factors, like the residual's constants, carry no derivative.
        solve, solve_consts = jax.closure_convert(approximate_solve, x0)
        solve_consts = jax.lax.stop_gradient(solve_consts)
        root, iterations, norm = iterate(
            lambda x: ((), value(x, *cut)), lambda _, r: solve(r, *solve_consts), guess
        )
    elif residual_and_jacobian is None:
        evaluate = functools.partial(_jacobian_and_value, lambda x: value(x, *cut))
        root, iterations, norm = iterate(evaluate, linear_solve, guess)
    else:
        root, iterations, norm = iterate(lambda x: both(x, *cut)[::-1], linear_solve, guess)
    # Tagged before `_at_root`, whose derivative rule evaluates `J` at this input: a
    # `jax.checkpoint` that keeps `ROOT_NAME` (`simulate`'s step) stores the root, and its
    # backward pass evaluates the derivative there without solving again.
    root = checkpoint_name(root, ROOT_NAME)
    x = _at_root(value, jacobian, linear_solve, root, *consts)
    iterations, norm = jax.lax.stop_gradient((iterations, norm))
    return x, NewtonInfo(iterations, norm, norm <= tolerance)


def _part(both, i, x, *consts):
    return both(x, *consts)[i]


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _at_root(value, jacobian, linear_solve, root, *consts):
    """`root`, a root of `value(·, *consts)`, with the derivative of the root as a function
    of `consts`."""
    return root


@_at_root.defjvp
def _at_root_jvp(value, jacobian, linear_solve, primals, tangents):
    # r(x(c), c) = 0 ⇒ J dx = −∂r/∂c dc: linear in the tangents with coefficients from the
    # primal point, so JAX transposes it for reverse mode (both solves are transposable).
    root, *consts = primals
    _, *dconsts = tangents
    _, dr = jax.jvp(lambda *c: value(root, *c), tuple(consts), tuple(dconsts))
    return root, -linear_solve(jacobian(root, *consts), dr)
