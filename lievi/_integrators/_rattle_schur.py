"""RATTLE's structured linear solve: the saddle-point system of its Newton iteration by the
Schur complement of the bodies' blocks.

The RATTLE equations (lievi/_integrators/_rattle.py) for the increments `ξ` `(N, 6)` and
the reaction impulses `Λ` `(c,)` are, scaled as the iteration scales them (`s` the size
of the momenta, `ℓ` the link length),

    r_ξ = (f(ξ) − m⁺ − Cᵀ Λ) / s,    r_Λ = Φ(g φ(ξ)) / ℓ,

with `f_i(ξ_i) = dφ⁻¹(ξ_i)ᵀ M_i ξ_i / h` depending on body `i`'s increment only and
`C = C(g_k)` constant. So their Jacobian has the structure of a constrained least-action
problem (a KKT matrix):

    J = [[A / s, −Cᵀ / s], [B / ℓ, 0]],   A = blockdiag(∂f_i/∂ξ_i),   B = ∂Φ(g φ(ξ))/∂ξ,

with `A` `N` blocks of 6×6 (≈ `M_i / h`) and `B` `c × 6N` (≈ `C` at `ξ = 0`). Eliminating
`dξ` leaves the `c × c` Schur complement `S = B A⁻¹ Cᵀ` (at `ξ = 0`: `h C M⁻¹ Cᵀ`, the
kinetic-metric Gram matrix of the joints), which has a block only where two joints share
a body (`lievi/_systems/_tree_solve.py`). Factored once — `N` inverses of 6×6 blocks and
the Schur complement by the joints' tree, without fill — a solve costs block products
and two products with `B` and `Cᵀ`: no dense `(6N + c)`-square factorisation and no
`jax.jacfwd` per iteration.

The blocks and the Schur complement's pivot blocks are inverted explicitly, once: an
iteration is then matrix products only, which XLA fuses, where a LAPACK triangular solve
per iteration costs more on CPU than the rest of the iteration. The inverses' rounding changes how fast
the iteration converges, not where: every iteration evaluates the exact residual.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._small_linalg import inverse as small_inverse
from .._small_linalg import matvec
from .._systems._tree_solve import block_tree_solver


def kkt_solver(blocks, B, C, scale, length, structure):
    """`r ↦ J⁻¹ r` for the RATTLE Jacobian `J` with momentum blocks `blocks` `(N, 6, 6)`
    (`∂f_i/∂ξ_i`, unscaled), constraint rows `B` and reaction directions `C`, both
    `JointRows` (`(c, N, 6)` kept by joint); `r` is `(6N + c,)`, the momentum residuals
    first (as the iteration stacks them). `structure`: the joints' tree
    (`ArticulatedBodies.joint_structure`), whose block pattern the Schur complement has."""
    n, c = blocks.shape[0], C.n_rows
    inverse = small_inverse(blocks)

    def block_solve(v):
        """`A⁻¹ v` for `v` `(N, 6)`: each body's block on its own rows."""
        return matvec(inverse, v)

    if c == 0:
        return lambda r: block_solve(scale * r.reshape(n, 6)).reshape(-1)

    # The Schur complement `B A⁻¹ Cᵀ` by its nonzero blocks (two joints sharing a body),
    # factored by the joints' tree: each joint's rows touch two bodies, so neither `A⁻¹ Cᵀ`
    # nor the products with `B` and `Cᵀ` are formed densely.
    schur_solve = block_tree_solver(B.gram_blocks(inverse, C, structure), structure)

    def solve(r):
        # A dξ − Cᵀ dΛ = s r_ξ and B dξ = ℓ r_Λ: with y = A⁻¹ s r_ξ,
        # S dΛ = ℓ r_Λ − B y and dξ = y + A⁻¹ Cᵀ dΛ.
        y = block_solve(scale * r[: 6 * n].reshape(n, 6))
        impulse = schur_solve(length * r[6 * n :] - B.apply(y))
        xi = y + block_solve(C.transpose_apply(impulse))
        return jnp.concatenate([xi.reshape(-1), impulse])

    return solve
