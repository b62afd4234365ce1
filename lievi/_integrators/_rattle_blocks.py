"""RATTLE's momentum blocks in closed form: `∂f_i/∂ξ_i` for
`f_i(ξ) = dφ⁻¹(ξ)ᵀ M_i ξ / h`, each body's side of its momentum equation, to O(|ξ|²).

Every chart of `lievi.RATTLE` (exp and Cayley) has `dφ⁻¹(ξ) = I − ½ ad_ξ + O(|ξ|²)`, so

    f(ξ) = (M ξ − ½ ad_ξᵀ M ξ) / h + O(|ξ|³/h),
    ∂f/∂ξ = (M − ½ ad_ξᵀ M − ½ K(M ξ)) / h + O(|ξ|²/h),   K(μ) η = ad_ηᵀ μ,

the same order as the joints' rows `C(g φ(ξ₀))(1 − ½ ad_ξ₀)` the iteration uses with it.
The block enters only the simplified Newton iteration's fixed Jacobian, at a guess
already O(h²) from the root: it changes how fast the iteration contracts (by O(|ξ|²)),
not the root, which every iteration's exact residual decides, nor the derivative, which
comes from the exact Jacobian at the root. `jax.jacfwd` of `f` instead differentiated
the chart's `dφ⁻¹` (its small-angle coefficients and their derivatives) along six
directions: under `jax.vmap` it was the largest part of a step.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._groups._se3 import SE3


def momentum_blocks(xi, tensor, h):
    """`∂f_i/∂ξ_i` `(N, 6, 6)` at the increments `xi` `(N, 6)`, to O(|ξ|²), for the kinetic
    tensors `tensor` `(N, 6, 6)` and the step `h`."""
    mu = jnp.einsum("nij,nj->ni", tensor, xi)
    ad = SE3.ad(xi)
    # `K(μ)[:, l] = ad_{e_l}ᵀ μ`: the coadjoint action as a matrix in its Lie-algebra slot.
    basis = SE3.ad(jnp.eye(6, dtype=xi.dtype))
    coad = jnp.einsum("lji,nj->nil", basis, mu)
    return (tensor - 0.5 * jnp.einsum("nji,njk->nik", ad, tensor) - 0.5 * coad) / h
