"""The preprocessed Moser–Veselov modified moments of a batch that shares one body, from a
few sample trajectories instead of one series computation per body.

The coefficient of `h^(2k)` in `α` (and in `β`) is a homogeneous polynomial of degree `k`
in the energy `H` and the Casimir `C` (scaling `Π → sΠ` scales `H`, `C` by `s²` and the
motion's frequency by `s`; the closed forms are polynomials in `h²H`, `h²C`), checked
numerically: fitted on 60 random momenta of three bodies, orders 8 and 10, the residual is
at round-off (≤ 5e-14 relative). So `α_{2k} = C^k p_k(e)`, `e = H/C`, with `p_k` a
polynomial of degree `k` on the energy range `[1/(2 I_max), 1/(2 I_min)]` of the unit
sphere. Its values at `order/2` Chebyshev nodes of that range (one series computation
each, on momenta of unit Casimir in the plane of the largest and smallest moments) fix it:
the Chebyshev–Vandermonde system at those nodes is solved by its discrete orthogonality
(a fixed matrix product, exact and well conditioned; differentiable in the inertia), and
each body then evaluates the polynomials in `(H, C)`, homogeneously (no division by `C`).
At a rotation exactly about a principal axis each body's series keeps `α = 1` (`α` is not
determined there) where the fit gives the nearby trajectories' value: the modified moment
of that axis, the only one the step sees, is the same.

Why: the per-body series arithmetic was most of a short batched run's cost (8–9 µs per
body at order 8, the step ~55 ns: at 25–100 steps the start-up dominated); the fit costs
the `order/2` series once per run and a few flops per body (`benchmarks/accuracy.py
--batch-cost`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def _nodes(n: int) -> np.ndarray:
    """The `n` Chebyshev nodes of the first kind on `(−1, 1)`: interior, so no sample is a
    rotation about a principal axis (where `α` is not determined by the momentum)."""
    return np.cos(np.pi * (np.arange(n) + 0.5) / n)


def _fit_matrix(n: int) -> np.ndarray:
    """`V⁻¹` for `V[i, j] = T_j(u_i)` at the nodes: `V⁻¹ = diag(w) Vᵀ`, `w = (1/n, 2/n, …)`
    (discrete orthogonality of the Chebyshev polynomials at these nodes)."""
    u = _nodes(n)
    V = np.cos(np.outer(np.arccos(u), np.arange(n)))
    weights = np.full(n, 2 / n)
    weights[0] = 1 / n
    return weights[:, None] * V.T


def _homogeneous_chebyshev(w, casimir, degree: int):
    """`[C^j T_j(w/C)]` for `j ≤ degree`: homogeneous of degree `j` in `(w, C)`, by the
    Chebyshev recurrence (no division; `w = C·u`)."""
    terms = [jnp.ones_like(w), w]
    for _ in range(2, degree + 1):
        terms.append(2 * w * terms[-1] - casimir**2 * terms[-2])
    return terms[: degree + 1]


def fitted_principal_moments(series, moments, m0s, h, order: int):
    """The modified principal moments `(B, 3)` of every body of a batch sharing the
    principal moments `moments` `(3,)`, from its momenta `m0s` `(B, 3)` and the step `h`
    (a scalar or `(B,)`): `modified_principal_moments` of each body, to round-off.
    `series`: `modified_moments_series` (passed in: that module builds the kernel)."""
    dtype = m0s.dtype
    n = order // 2  # p_k has degree k ≤ order/2 − 1
    inverse = 1 / moments
    ranks = jnp.argsort(moments)
    # The unit sphere's energies run from 1/(2 I_max) (axis `low`) to 1/(2 I_min) (`high`).
    low, high = jax.nn.one_hot(ranks[2], 3, dtype=dtype), jax.nn.one_hot(ranks[0], 3, dtype=dtype)
    e_low, e_high = inverse @ low / 2, inverse @ high / 2
    u = jnp.asarray(_nodes(n), dtype)[:, None]
    samples = jnp.sqrt((1 - u) / 2) * low + jnp.sqrt((1 + u) / 2) * high  # |m| = 1, H = e(u)
    alphas, betas = jax.vmap(lambda m: series(jnp.diag(inverse), m, order - 2))(samples)
    fit = jnp.asarray(_fit_matrix(n), dtype)
    # Chebyshev coefficients `[k, j]` of p_k (row k: the coefficient of h^(2k)), j ≤ k:
    # by the orthogonality, the same as fitting degree k alone (the rest are round-off).
    degree_mask = jnp.asarray(np.tri(n), dtype)
    alpha_fit = (fit @ alphas[:, 0::2]).T * degree_mask
    beta_fit = (fit @ betas[:, 0::2]).T * degree_mask

    casimir = jnp.sum(m0s**2, axis=-1)
    energy = m0s**2 @ inverse / 2
    spread = e_high - e_low
    safe_spread = jnp.where(spread > 0, spread, 1)  # a spherical body: every p_k constant
    w = (2 * energy - (e_low + e_high) * casimir) / safe_spread
    basis = _homogeneous_chebyshev(w, casimir, n - 1)
    h2 = jnp.asarray(h, dtype) ** 2
    alpha, beta = jnp.ones_like(casimir), jnp.zeros_like(casimir)
    for k in range(1, n):
        scale = h2**k
        alpha += scale * sum(alpha_fit[k, j] * casimir ** (k - j) * basis[j] for j in range(k + 1))
        beta += scale * sum(beta_fit[k, j] * casimir ** (k - j) * basis[j] for j in range(k + 1))
    return 1 / (alpha[:, None] / moments + beta[:, None])
