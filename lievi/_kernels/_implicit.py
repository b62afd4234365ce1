"""The derivative of a kernel's Newton root: the implicit function theorem, once for every
kernel (paper (4.8) is solved by Newton; its root is differentiated, not the iterations).

A kernel's equation is an object with `residual(x, m, A, with_jacobian) -> (r, J)` (the
closed-form residual of the step's implicit equation in structure of arrays, and its
Jacobian) and `solve(J, r) -> J⁻¹r`: `_so3_equations.AbstractSO3Equation` and
`_se3_residual.SE3Equation`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from ._base import ROOT_NAME, materialise, ones


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _at_root(equation, x, m, A):
    """`x`, a root of `r(·; m, A)`, with the derivative of the root as a function of `(m, A)`."""
    return x


@_at_root.defjvp
def _at_root_jvp(equation, primals, tangents):
    # r(x(m, A); m, A) = 0 ⇒ J dx = −(∂r/∂m dm + ∂r/∂A dA): linear in the tangents with
    # coefficients from the primal point, so JAX transposes it for reverse mode, and the
    # transposed solve costs what the forward one does.
    x, m, A = primals
    _, dm, dA = tangents
    _, dr = jax.jvp(lambda mm, AA: equation.residual(x, mm, AA, False)[0], (m, A), (dm, dA))
    _, J = equation.residual(x, m, A, True)
    # Materialised: in reverse mode this is the transposed solve's result `λ = J⁻ᵀ x̄`, which
    # every cotangent of `m` and `A` needs; stored once rather than the solve (with `J`)
    # re-evaluated inside each of their fused loops (measured on SO(3): the gradient of a
    # batch of 1e5 exp-chart bodies 16 % faster).
    dr = materialise(dr, ones(x[0]))
    delta = equation.solve(J, dr)
    return x, tuple(-d for d in delta)


def differentiable_root(equation, x, guess, m, A):
    """The Newton root `x` (computed from `stop_gradient`-ed inputs) as a differentiable
    function of `(m, A)`.

    A diverged solve (reported through the residual) continues from the finite `guess`:
    the implicit derivative is then evaluated at a finite point, so a failed step whose
    output is masked contributes 0, not NaN, to a gradient. The root is tagged
    `ROOT_NAME` before `_at_root`, whose derivative rule evaluates `J` at this input: the
    backward pass of a `jax.checkpoint`-ed step finds it stored (a tag on the output alone
    is a different variable, and the backward pass would re-run the Newton iterations).
    """
    finite = jnp.isfinite(x[0])
    for y in x[1:]:
        finite = finite & jnp.isfinite(y)
    x = tuple(jnp.where(finite, y, y0) for y, y0 in zip(x, guess))
    x = checkpoint_name(jax.lax.stop_gradient(x), ROOT_NAME)
    return _at_root(equation, x, m, A)
