"""Newton for the SE(3) DEP equation (paper (4.8)) on small arrays, for the forward step.

The same residual `r = dφ⁻¹(ξ)ᵀ μ − m` and Jacobian `dφ⁻¹(ξ)ᵀ A + E` as the scalar forms
of `_se3_dep.py` (derived there; the tests compare both with `jax.jacfwd` of the generic
residual), written on `(3,)`, `(3, 3)` and `(6, 6)` arrays: `ξ̂` as a sum of constant
matrices, blocks placed by padding, the Newton system solved by Gauss–Jordan elimination
without pivoting (as `_se3_dep.solve6`, it relies on `J = M/h + O(|ξ|)` with `M` positive
definite). Why arrays here: XLA on CPU runs every scalar leaf of a concatenation as its own
kernel, and with `_barrier` the scalar Newton iteration is about a hundred kernels whose
launch costs dominate one body's step; elementwise array expressions fuse, and an
iteration here is about thirty kernels. Under `vmap` it is no slower per body than the
scalar form either (measured faster: `benchmarks/se3_step_cost.py`, docs/se3.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import _se3_dep  # (at call time: it imports this module)

# ŷ = Σₖ yₖ Hₖ with constant Hₖ: elementwise, so it fuses (a stack of entries would not).
_HATS = np.stack([np.cross(np.eye(3), e) for e in np.eye(3)])  # Hₖ = êₖ
_ROWS = np.eye(6, dtype=bool)


def _hat(y):
    H = _HATS.astype(y.dtype)
    return H[0] * y[0] + H[1] * y[1] + H[2] * y[2]


def _eye(dtype):
    return jnp.eye(3, dtype=dtype)


def _outer(x, y):
    return x[:, None] * y[None, :]


def _blocks(B11, B12, B21, B22):
    """The 6×6 matrix `[[B11, B12], [B21, B22]]`, by padding (fuses; a concatenation does not)."""
    return (
        jnp.pad(B11, ((0, 3), (0, 3)))
        + jnp.pad(B12, ((0, 3), (3, 0)))
        + jnp.pad(B21, ((3, 0), (0, 3)))
        + jnp.pad(B22, ((3, 0), (3, 0)))
    )


def _dot(x, y):
    # Written out: an elementwise expression fuses into its consumer, a reduction would not.
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _point(chart: str, x, A):
    """What the residual and the Jacobian at `x` share: `(x, μ = A x, (c, c′, c″), dφ⁻¹(x)ᵀ)`
    (the coefficients zero for Cayley). Newton computes it once an iterate."""
    w, v = x[:3], x[3:]
    mu = A @ x
    t, s = _dot(w, w), _dot(w, v)
    zero, I3 = jnp.zeros((3, 3), x.dtype), _eye(x.dtype)
    if chart == "cayley":
        # K = 1 + ω̂/2 + ωωᵀ/4, K′ = 1 + ω̂/2, L = v̂K′/2 = v̂/2 + (ωvᵀ − s)/4.
        Kp = I3 + _hat(w) / 2
        D = _blocks(Kp + _outer(w, w) / 4, _hat(v) / 2 + (_outer(w, v) - s * I3) / 4, zero, Kp)
        return x, mu, jnp.zeros(3, x.dtype), D
    c, c1, c2 = _se3_dep._dexpinv_coefficient(t)
    k = 2 * c1 * s
    # K = K′ = (1 − ct) + ω̂/2 + c ωωᵀ, L = v̂/2 + 2c′s(ωωᵀ − t) + c(ωvᵀ + vωᵀ − 2s).
    K = (1 - c * t) * I3 + _hat(w) / 2 + c * _outer(w, w)
    L = (
        _hat(v) / 2
        - (k * t + 2 * c * s) * I3
        + k * _outer(w, w)
        + c * (_outer(w, v) + _outer(v, w))
    )
    return x, mu, jnp.stack([c, c1, c2]), _blocks(K, L, zero, K)


def _jacobian(chart: str, point, A):
    """`∂r/∂ξ = dφ⁻¹(ξ)ᵀ A + E` at a `_point`."""
    x, mu, coefficients, D = point
    w, v, a, b = x[:3], x[3:], mu[:3], mu[3:]
    t, s, oa, ob, vb = _dot(w, w), _dot(w, v), _dot(w, a), _dot(w, b), _dot(v, b)
    zero, I3 = jnp.zeros((3, 3), x.dtype), _eye(x.dtype)
    if chart == "cayley":
        Kpb = b + _hat(w) @ b / 2
        E_ww = -_hat(a) / 2 + (oa + vb) / 4 * I3 + (_outer(w, a) - _outer(b, v)) / 4
        return D @ A + _blocks(E_ww, -_hat(Kpb) / 2, -_hat(b) / 2, zero)
    c, c1, c2 = coefficients[0], coefficients[1], coefficients[2]
    k = 2 * c1 * s
    # `_se3_dep._blocks`'s E, its rank-one terms grouped by their right factor:
    # E_ωω = ∂_ω(K a) + ∂_ω(L b), and ∂_v(L b) = ∂_ω(K b) (the same matrix, D_b).
    za, zb = w * oa - t * a, w * ob - t * b  # ω̂²a, ω̂²b
    lw = w * vb + v * ob - 2 * s * b
    y = 2 * c1 * zb - 2 * c * b
    u = -2 * c * a + 2 * c1 * (za + lw) + 4 * s * (c2 * zb - c1 * b)
    E_ww = (
        -_hat(a) / 2
        + (c * (oa + vb) + k * ob) * I3
        + _outer(w, c * a + k * b)
        + _outer(v, c * b)
        + _outer(u, w)
        + _outer(y, v)
    )
    D_b = -_hat(b) / 2 + c * ob * I3 + _outer(w, c * b) + _outer(y, w)
    return D @ A + _blocks(E_ww, D_b, D_b, zero)


def residual(chart: str, x, m, A, with_jacobian: bool):
    """`(r, J)` of `_se3_dep.residual` on arrays: `x`, `m` `(6,)`, `A = M/h` `(6, 6)`."""
    point = _point(chart, x, A)
    r = point[3] @ point[1] - m
    return r, (_jacobian(chart, point, A) if with_jacobian else None)


def solve(J, r):
    """`J⁻¹ r` by Gauss–Jordan elimination on `[J | r]`, no pivoting (see the module doc)."""
    aug = jnp.concatenate([J, r[:, None]], axis=1)
    for k in range(6):
        pivot_row = aug[k] / aug[k, k]
        aug = jnp.where(_ROWS[k][:, None], pivot_row, aug - aug[:, k : k + 1] * pivot_row)
    return aug[:, 6]


def newton(chart: str, guess, m, A, tolerance, max_steps: int):
    """Newton from `guess` until `‖r‖_∞ ≤ tolerance` (or non-finite, or `max_steps`):
    `(x, ‖r‖_∞, iterations)`, the iterates of `_se3_dep`'s scalar Newton (to round-off).
    A `while_loop`: not differentiated (`_se3_dep._at_root` gives the derivative). The
    residual's `_point` at each iterate is carried to the next iteration's Jacobian."""

    def at(x):
        point = _point(chart, x, A)
        r = point[3] @ point[1] - m
        return point, r, jnp.max(jnp.abs(r))

    def cond(carry):
        _, _, n, it = carry
        return (n > tolerance) & jnp.isfinite(n) & (it < max_steps)

    def body(carry):
        point, r, _, it = carry
        return *at(point[0] - solve(_jacobian(chart, point, A), r)), it + 1

    point, _, n, it = jax.lax.while_loop(cond, body, (*at(guess), jnp.zeros((), jnp.int32)))
    return point[0], n, it
