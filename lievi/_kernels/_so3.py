"""A fast batched DEP/DLP step for the free rigid body on SO(3) (paper (4.8), (3.3), (2.9)).

The same discrete Euler–Poincaré equation as `DEP` (`_dep.py`), for a rigid body with
principal moments `I` (diagonal inertia), written for throughput over many bodies:

- **structure of arrays**: every vector or matrix component is its own `(B,)` array with
  the batch as the minor (contiguous) axis, so XLA emits long elementwise loops that it
  vectorises and fuses into a few kernels; batched 3×3 `matmul`/`solve`/`jacfwd` on
  `(B, 3, 3)` arrays vectorise poorly on CPU (docs/performance.md);
- **closed forms**: the residual `r(ξ) = dφ⁻¹(ξ)ᵀ I ξ/h − Π_k` and its 3×3 Jacobian are
  written out by hand (derived below; the tests check them against `jax.jacfwd` of the
  generic residual) and the Newton system is solved by Cramer's rule;
- **no library trigonometry**: on CPU `jnp.sin` is a scalar libm call (~12× slower than a
  12-term polynomial in the same loop, measured). Every coefficient is a function of
  `u = θ²/4` (`θ = |ξ|`, `φ = θ/2`) and is evaluated as a power series that is accurate
  to round-off for `θ ≤ π` (the exp chart's domain) and free of cancellation:
  `S(u) = sin φ/φ`, `C(u) = cos φ`, `P(u) = (S − C)/u`, hence
  `sin θ/θ = S C`, `(1 − cos θ)/θ² = S²/2` and the `dexpinv` coefficient
  `(1 − (θ/2)cot(θ/2))/θ² = P/(4S)` (docs/theory/closed-forms.md);
- **implicit differentiation**: the converged root is passed through
  `_implicit.differentiable_root`, whose derivative is the implicit function theorem's `dξ = −J⁻¹ (∂r/∂Π dΠ + ∂r/∂A dA)` with
  the closed-form `J` (Cramer's rule again, so the transposed solve of reverse mode costs
  what a forward Newton iteration does); the Newton iterations themselves, and their
  `while_loop`, run on `stop_gradient`-ed inputs and are never differentiated;
- **a Newton policy for batches**: a fixed number of Newton iterations (no convergence
  test, so no lane waits and nothing breaks the fusion), then one residual check per
  body; only if some body is still above its tolerance does a `while_loop` continue —
  on those bodies only — up to `max_steps`. A body that does not converge gets
  `RESULTS.newton_not_converged` and does not stop the others.

Derivation (left-invariant, `A = diag(I)/h`, `w = Aξ`, `d = ξ·w`, `t = θ²`):
`dexpinv(ξ)ᵀ = 1 + ξ̂/2 + c(t) ξ̂²` with `ξ̂² w = ξ d − t w`, so

    exp:    r = w + ½ ξ×w + c (ξ d − t w) − Π,
            J = A + ½(ξ̂A − ŵ) + 2c′ (ξ d − t w) ξᵀ + c (d 1 + 2ξwᵀ − 2wξᵀ − t A);
    cayley: r = w + ½ ξ×w + ¼ ξ d − Π,          (dcayinv(ξ)ᵀ = 1 + ξ̂/2 + ξξᵀ/4)
            J = A + ½(ξ̂A − ŵ) + ¼ (d 1 + 2ξwᵀ);

then `F = φ(ξ) = 1 + a ξ̂ + b ξ̂²` (exp: `a = S C`, `b = S²/2`; Cayley: `a = 4/(4 + t)`,
`b = a/2`), `Π_{k+1} = Fᵀ Π_k = Π − a ξ×Π + b(ξ(ξ·Π) − tΠ)` (DLP 3.3) and
`g_{k+1} = g_k F` (2.9).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._newton import newton_tolerance
from .._results import RESULTS
from ._base import AbstractBatchKernel, materialise, ones
from ._flat_batch import bodies_batched
from ._implicit import differentiable_root
from ._so3_equations import AbstractSO3Equation, explicit_euler_guess, moser_veselov_on_branch
from ._soa import (
    cross,
    dot,
    max_abs,
    rotate_rows,
    solve3,
)


def solve_increment(equation, m, A, tolerance, fixed_iterations: int, max_steps: int, alive=True):
    """Newton for the DEP equation on a batch: `fixed_iterations`, then a check.

    Returns `(ξ, iterations, residual ∞-norm, converged)`, all per body. For Moser–Veselov
    the fixed iterations are scalar Newton iterations (`_moser_veselov_by_scalar_newton`);
    any further ones, for the bodies still above tolerance, are Newton steps in `x`.
    Bodies where `alive` is false (already failed) take no iterations past the fixed ones.
    Not differentiable (a `while_loop`); `differentiable_increment` is.
    """
    fixed = min(fixed_iterations, max_steps)
    restartable = equation.restartable()
    xi = equation.start(m, A, fixed)
    r, _ = equation.residual(xi, m, A, False)
    norm = max_abs(r)
    if restartable:
        # A root of the quartic off the branch rule (`moser_veselov_on_branch`) is not
        # the generic path's root: such a body restarts from the explicit-Euler guess.
        norm = jnp.where(moser_veselov_on_branch(xi, m, A), norm, jnp.inf)
    iterations = jnp.full(norm.shape, fixed, jnp.int32)

    def active(norm, iterations):
        # Bodies stop at max_steps like `DEP`; a lane that has stopped is inactive.
        return alive & (norm > tolerance) & jnp.isfinite(norm) & (iterations < max_steps)

    def cond(carry):
        _, norm, iterations = carry
        return jnp.any(active(norm, iterations))

    def body(carry):
        xi, norm, iterations = carry
        on = active(norm, iterations)
        r, J = equation.residual(xi, m, A, True)
        delta = solve3(J, r)
        xi = tuple(jnp.where(on, xi[i] - delta[i], xi[i]) for i in range(3))
        r, _ = equation.residual(xi, m, A, False)
        norm = jnp.where(on, max_abs(r), norm)
        return xi, norm, iterations + on.astype(jnp.int32)

    def restart(carry):
        # A body the scalar iteration left unconverged and worse off than the
        # explicit-Euler guess (far from the root, on another root of the quartic, or
        # non-finite) continues from that guess, as the three-dimensional Newton of
        # `MoserVeselov` would have started. Once, on entering the tail.
        xi, norm, iterations = carry
        guess = explicit_euler_guess(m, A)
        guess_norm = max_abs(equation.residual(guess, m, A, False)[0])
        back = ~(norm <= tolerance) & ~(norm <= guess_norm)
        xi = tuple(jnp.where(back, guess[i], xi[i]) for i in range(3))
        # A restarted body gets the generic path's full budget of `max_steps` Newton
        # steps from the guess, so both paths end on the same iterate.
        return (xi, jnp.where(back, guess_norm, norm), jnp.where(back, 0, iterations)), back

    def tail(carry):
        if restartable:
            carry, back = restart(carry)
            xi, norm, iterations = jax.lax.while_loop(cond, body, carry)
            return xi, norm, iterations + jnp.where(back, fixed, 0)
        return jax.lax.while_loop(cond, body, carry)

    if max_steps > fixed:
        # The tail (and the restart's extra residual) only when some body needs it.
        unfinished = jnp.any(alive & ~(norm <= tolerance))
        xi, norm, iterations = jax.lax.cond(unfinished, tail, lambda c: c, (xi, norm, iterations))
    return xi, iterations, norm, norm <= tolerance


def differentiable_increment(
    equation, m, A, tolerance, fixed_iterations: int, max_steps: int, alive=True
):
    """`solve_increment` whose `ξ` differentiates by the implicit function theorem at the root.

    The Newton iterations run on `stop_gradient`-ed inputs (so no `while_loop` is
    differentiated); the root is tagged `ROOT_NAME` for `jax.checkpoint` policies.
    """
    stopped = jax.lax.stop_gradient((m, A, tolerance))

    def solve(m, A, tolerance, alive):
        return solve_increment(equation, m, A, tolerance, fixed_iterations, max_steps, alive)

    xi, iterations, norm, converged = bodies_batched(solve)(*stopped, jnp.asarray(alive))
    guess = explicit_euler_guess(*stopped[:2])
    return differentiable_root(equation, xi, guess, m, A), iterations, norm, converged


def dep_step(equation, g, m, A, tolerance, fixed_iterations: int, max_steps: int, alive=True):
    """One DEP + DLP + reconstruction step on structure-of-arrays state.

    `equation`: `DEPEquation(chart)` (`DEP`) or `MoserVeselovEquation()` (`MoserVeselov`:
    the Cayley chart with the Moser–Veselov residual).
    `g`: 9 arrays (row-major), or the rows of `g` that are carried (3 arrays a row: each
    row `r` becomes `r F`, so the reduced state's `Γᵀ = aᵀg` is one row), `m`: 3 arrays,
    `A = I/h`: 3 arrays (or scalars).
    Returns `(g_next, Pi_next, result, iterations, residual)`; reverse-mode differentiable.
    """
    xi, iterations, norm, converged = differentiable_increment(
        equation, m, A, tolerance, fixed_iterations, max_steps, alive
    )
    t = dot(xi, xi)
    # Stored once: each of the 12 entries of `g_{k+1}` and `Π_{k+1}` reads them (the exp
    # chart's are power series, else recomputed in each).
    a, b = materialise(equation.increment_coefficients(t), ones(t))
    off_branch = equation.off_branch(jax.lax.stop_gradient(xi), m, A, t, converged)
    g_next = rotate_rows(g, xi, a, b)
    xp = cross(xi, m)
    dp = dot(xi, m)
    m_next = tuple(m[i] - a * xp[i] + b * (xi[i] * dp - t * m[i]) for i in range(3))

    result = jnp.where(converged, RESULTS.successful, RESULTS.newton_not_converged)
    result = jnp.where(off_branch, RESULTS.step_too_large, result)
    finite = jnp.isfinite(norm)
    for p in m_next:
        finite = finite & jnp.isfinite(p)
    result = jnp.where(finite, result, RESULTS.nonfinite)
    return g_next, m_next, result.astype(jnp.int32), iterations, norm


class NewtonKernel(AbstractBatchKernel):
    """The implicit step (`dep_step`) of `DEP` (both charts) or `MoserVeselov`.

    `equation`: a `DEPEquation` or `MoserVeselovEquation`; `rtol`, `atol`, `max_steps`: the
    integrator's; `fixed_iterations`: see `solve_increment` (default: the equation's).
    """

    equation: AbstractSO3Equation = eqx.field(static=True)
    rtol: float | None = eqx.field(static=True)
    atol: float | None = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    fixed_iterations: int | None = eqx.field(default=None, static=True)

    def prepare(self, inertia, h):
        return tuple(moment / h for moment in inertia)

    def step(self, params, g, m, alive):
        fixed = self._fixed()
        # The tolerance policy of every implicit step (`simulate`'s too): relative by default.
        tolerance = newton_tolerance(max_abs(m), m[0].dtype, self.rtol, self.atol)
        return dep_step(self.equation, g, m, params, tolerance, fixed, self.max_steps, alive)

    def with_fixed_iterations(self, fixed_iterations: int):
        return dataclasses.replace(self, fixed_iterations=fixed_iterations)

    def _fixed(self) -> int:
        """The fixed Newton iterations of a step: as set, or the default."""
        fixed = self.fixed_iterations
        return self.equation.fixed_iterations() if fixed is None else fixed
