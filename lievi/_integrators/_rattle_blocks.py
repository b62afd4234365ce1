"""RATTLE's momentum blocks in closed form: `∂f_i/∂ξ_i` for
`f_i(ξ) = dφ⁻¹(ξ)ᵀ M_i ξ / h`, each body's side of its momentum equation.

With `dφ⁻¹(ξ) = I − ½ ad_ξ + c₂ ad_ξ² + …` (the chart's `ad_squared`: 1/12 for exp, whose
block is then exact to O(|ξ|³); 0 for Cayley, whose second-order term is not of this form,
exact to O(|ξ|²)) and `K(μ) η = ad_ηᵀ μ`,

    f(ξ) ≈ (M ξ − ½ ad_ξᵀ M ξ + c₂ (ad_ξᵀ)² M ξ) / h,
    ∂f/∂ξ ≈ (M − ½ (ad_ξᵀ M + K(Mξ)) + c₂ (K(ad_ξᵀ Mξ) + ad_ξᵀ (K(Mξ) + ad_ξᵀ M))) / h.

The block enters only the simplified Newton iteration's fixed Jacobian, at a guess
already O(h²) from the root: it changes how fast the iteration contracts, not the root,
which every iteration's exact residual decides, nor the derivative, which comes from the
exact Jacobian at the root. `jax.jacfwd` of `f` instead differentiated the chart's `dφ⁻¹`
(its small-angle coefficients and their derivatives) along six directions: under
`jax.vmap` it was the largest part of a step. Without the exp chart's `ad²` term a
floating chain translating fast took twice the iterations.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._groups._se3 import SE3


def momentum_blocks(xi, tensor, h, ad_squared):
    """`∂f_i/∂ξ_i` `(N, 6, 6)` at the increments `xi` `(N, 6)` for the kinetic tensors
    `tensor` `(N, 6, 6)`, the step `h` and the chart's `ad_squared` coefficient."""
    mu = jnp.einsum("nij,nj->ni", tensor, xi)
    adT = jnp.swapaxes(SE3.ad(xi), -1, -2)
    # `K(μ)[:, l] = ad_{e_l}ᵀ μ`: the coadjoint action as a matrix in its Lie-algebra slot.
    basis = SE3.ad(jnp.eye(6, dtype=xi.dtype))

    def coad(w):
        return jnp.einsum("lji,nj->nil", basis, w)

    first = tensor - 0.5 * (adT @ tensor + coad(mu))
    w = jnp.einsum("nij,nj->ni", adT, mu)
    second = coad(w) + adT @ (coad(mu) + adT @ tensor)
    return (first + ad_squared * second) / h
