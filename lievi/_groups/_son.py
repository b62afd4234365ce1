"""The special orthogonal groups SO(n), n ≥ 2 (the generalized rigid body, paper §4.2, §5).

Algebra coordinates. `so(n)` has dimension `d = n(n−1)/2`. Coordinate `p` belongs to the
plane `(i, j)`, `i < j` (zero-based), with the planes listed in *decreasing*
lexicographic order, and

    x̂[j, i] = s_p x_p,   x̂[i, j] = −s_p x_p,   s_p = (−1)^(i+j+1).

For n = 3 the planes are (1,2), (0,2), (0,1) and this is exactly the usual hat map of
`R³` (`x̂ y = x × y`), so `SOn(3)` and `SO3` share coordinates. The basis is orthonormal
for `⟨X, Y⟩ = tr(XᵀY)/2`, so `|x|` is the Frobenius norm of `x̂` over √2.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import membership_tolerance
from ._base import MatrixLieGroup
from ._eager import compiled_when_eager


@functools.cache
def planes(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pairs = sorted(((i, j) for i in range(n) for j in range(i + 1, n)), reverse=True)
    i = np.array([p[0] for p in pairs], dtype=np.int32)
    j = np.array([p[1] for p in pairs], dtype=np.int32)
    sign = np.where((i + j + 1) % 2 == 0, 1.0, -1.0)
    return i, j, sign


class AbstractSpecialOrthogonal(MatrixLieGroup):
    """Shared structure of SO(n): hat/vee in the basis above, `g⁻¹ = gᵀ`, a log."""

    @property
    def algebra_dim(self) -> int:
        n = self.matrix_dim
        return n * (n - 1) // 2

    def hat(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch n n"]:
        n = self.matrix_dim
        i, j, sign = planes(n)
        if x.shape[-1] != len(i):
            raise ValueError(
                f"so({n}) coordinates must have last axis {len(i)}, got shape {x.shape}."
            )
        signed = x * jnp.asarray(sign, x.dtype)
        X = jnp.zeros(x.shape[:-1] + (n, n), x.dtype)
        return X.at[..., j, i].set(signed).at[..., i, j].set(-signed)

    def rotation(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
        """`g` itself: an element of SO(n) is a rotation (it has no translation)."""
        return g

    def vee(self, X: Float[Array, "*batch n n"]) -> Float[Array, "*batch d"]:
        i, j, sign = planes(self.matrix_dim)
        # The skew part's coordinates: exact on so(n), a projection elsewhere.
        return jnp.asarray(sign, X.dtype) * (X[..., j, i] - X[..., i, j]) / 2

    @property
    def exp_radius(self) -> float:
        # |x| = (Σ θ_i²)^½ over the rotation planes bounds the largest angle θ_i from above.
        return float(jnp.pi)

    def inverse(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
        return jnp.swapaxes(g, -1, -2)

    def project(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
        """One Newton–Schulz step of the polar decomposition, `g ← g(3I − gᵀg)/2`: maps an
        orthogonality defect `δ` to `O(δ²)`."""
        eye = jnp.eye(g.shape[-1], dtype=g.dtype)
        return g - g @ (jnp.swapaxes(g, -1, -2) @ g - eye) / 2

    def membership_defect(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch"]:
        """`‖gᵀg − I‖_F + |det g − 1|` (the determinant term catches reflections)."""
        eye = jnp.eye(self.matrix_dim, dtype=g.dtype)
        orthogonality = jnp.linalg.norm(jnp.swapaxes(g, -1, -2) @ g - eye, axis=(-2, -1))
        return orthogonality + jnp.abs(jnp.linalg.det(g) - 1)

    def membership_hint(self) -> str:
        return (
            "‖gᵀg − I‖ + |det g − 1| must vanish; pass a rotation matrix, e.g. orthonormalise "
            "with a QR or polar decomposition"
        )

    def casimirs(self, m: Float[Array, "*batch d"]) -> Float[Array, "*batch k"]:
        """`−tr(m̂^{2k})/2` for `k = 1 … ⌊n/2⌋` (the odd traces vanish on skew matrices);
        on SO(3) the single Casimir is `|Π|²`."""
        M = self.hat(m)
        M2 = M @ M
        power = M2  # m̂^{2k}
        traces = []
        for _ in range(self.matrix_dim // 2):
            traces.append(-jnp.trace(power, axis1=-2, axis2=-1) / 2)
            power = power @ M2
        return jnp.stack(traces, axis=-1)

    def log(self, g: Float[Array, "*batch n n"], iterations: int = 1):
        """Principal logarithm: `x` with `exp(x) = g`, every rotation angle in `[0, π]`.

        Contract: `g` must be a rotation (use `log_checked` for input that may not be one:
        it returns NaN for a non-rotation). The result is *verified*: `exp(x) = g` to a
        few hundred ulps, or the result is NaN — never a wrong finite number. Away from
        half-turns `x` comes from the polar/Gregory route below; where that route loses
        accuracy (a rotation angle within ~1e-5 of π) it comes from the symmetric-part
        formula `_log_half_turn`, exact up to and at π (for an exact half-turn, one of the
        equally valid logarithms). A rotation with two or more angles at π within
        round-off of each other (e.g. `−I` in SO(4)) has no well-conditioned logarithm;
        there the result may be NaN.

        Away from half-turns:

        `x = 2³ log(g^{1/8})`: three principal square roots (polar factors of `I + g`)
        bring every rotation angle below π/8, where the Gregory series
        `log h = 2 artanh W`, `W = (h − I)(h + I)⁻¹` converges fast. This start is
        accurate to about `ε/(π − θ)` for a largest angle `θ` (forming `I + g` cancels
        near a half-turn), and its derivative to about `ε/(π − θ)²`.

        It is then refined by `iterations` Newton steps on `exp(x) = g` in the left
        trivialisation, `x ← x + dexpinv(−x) · vee(exp(−x) g)`. One step brings the value
        to round-off up to `π − 1e-7`, and since the Newton map has zero derivative at
        its fixed point, the derivative of the result is the exact derivative of `log`.
        The first step needs no matrix exponential: `exp(x) = h⁸` for `h = g^{1/8}`, and
        `dexp(−x)` follows from `dexp(−x/8)` (a short power series) by the doubling
        formula `dexp(2z) = ½(I + Ad_{exp z}) dexp(z)`. Further steps use `exp` and
        `dexpinv`.

        At an angle of exactly π the principal logarithm is not unique; this route is not
        finite there, and the half-turn route takes over.
        """
        x = self._log_polar(g, iterations)
        accurate = self._log_accurate(g, x)
        # Near a half-turn: the symmetric-part route, polished by one Newton step from a
        # constant start (its derivative is then the exact derivative of log, as above).
        x0 = jax.lax.stop_gradient(self._log_half_turn(g))
        x_half = x0 + jnp.einsum(
            "...ab,...b->...a", self.dexpinv(-x0), self.vee(self.inverse(self.exp(x0)) @ g)
        )
        x = jnp.where(accurate[..., None], x, x_half)
        verified = accurate | self._log_accurate(g, x)
        return jnp.where(verified[..., None], x, jnp.nan)

    def log_checked(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch d"]:
        """`log(g)`, or NaN where `g` is not a rotation (membership defect
        `‖gᵀg − I‖_F + |det g − 1|` above `membership_tolerance`: 1e-6, 64 ulps in float32)."""
        inside = self.membership_defect(g) <= membership_tolerance(g.dtype)
        eye = jnp.eye(self.matrix_dim, dtype=g.dtype)
        safe = jnp.where(inside[..., None, None], g, eye)
        return jnp.where(inside[..., None], self.log(safe), jnp.nan)

    def _log_accurate(self, g, x):
        """`‖exp(x) − g‖_max` within a few hundred ulps (per batch element)."""
        eps = jnp.finfo(g.dtype).eps
        error = jnp.max(jnp.abs(self.exp(x) - g), axis=(-2, -1))
        return jnp.all(jnp.isfinite(x), axis=-1) & (error <= 256 * self.matrix_dim * eps)

    def _log_half_turn(self, g):
        """The logarithm from the symmetric and skew parts, accurate up to and at π.

        For `g = exp(X)`: `S = (g + gᵀ)/2 = cos X`, `K = (g − gᵀ)/2 = sin X`, and `X`
        commutes with both. In an eigenbasis `V` of `S` (eigenvalues `cos θ`), `K̃ = VᵀKV`
        is block diagonal over equal eigenvalues, each row `a` of norm `sin θ_a`;
        `θ_a = atan2(‖K̃_a‖, c_a)` is accurate to an ulp at every angle (unlike `acos c`
        or `asin s`), and `X̃ = θ K̃ / sin θ` blockwise. At an exact half-turn (`K̃ ≈ 0`
        on an eigenvalue −1) the plane's orientation is free: the eigenvectors are paired
        and each pair rotated by π. Eigenvectors are not differentiable at repeated
        eigenvalues; the caller takes no derivative through this function.
        """
        dtype = g.dtype
        eps = jnp.finfo(dtype).eps
        S = (g + jnp.swapaxes(g, -1, -2)) / 2
        K = (g - jnp.swapaxes(g, -1, -2)) / 2
        c, V = jnp.linalg.eigh(S)
        Kt = jnp.swapaxes(V, -1, -2) @ K @ V
        # Entries between different eigenvalues are round-off (exactly 0 for exact input):
        # dropped, also from the row norms (for a small sin θ they would bias it).
        same = jnp.abs(c[..., :, None] - c[..., None, :]) <= jnp.sqrt(eps)
        Kt = jnp.where(same, Kt, 0.0)
        s = jnp.sqrt(jnp.sum(Kt * Kt, axis=-1))
        theta = jnp.arctan2(s, c)
        half = (s <= 16 * eps) & (c < 0)
        psi = jnp.where(s > 0, theta / jnp.where(s > 0, s, 1.0), 1.0)
        Xt = Kt * (psi[..., :, None] + psi[..., None, :]) / 2
        # Exact half-turns: pair eigenvectors (0, 1), (2, 3), … of the eigenvalue −1
        # (sorted first by `eigh`; its multiplicity is even on SO(n)).
        n = self.matrix_dim
        pair = np.zeros((n, n))
        for a in range(0, n - 1, 2):
            pair[a + 1, a], pair[a, a + 1] = 1.0, -1.0
        both = half[..., :, None] & half[..., None, :]
        Xt = jnp.where(both, jnp.pi * jnp.asarray(pair, dtype), Xt)
        X = V @ Xt @ jnp.swapaxes(V, -1, -2)
        return self.vee(X)

    def _log_polar(self, g, iterations: int):
        """The polar/Gregory route of `log` with `iterations` Newton steps (see `log`)."""
        # Loops are `fori_loop`s rather than Python loops: that compiles several times faster.
        dtype = g.dtype
        eye = jnp.eye(self.matrix_dim, dtype=dtype)
        h = jax.lax.fori_loop(0, _ROOTS, lambda _, h: _rotation_sqrt(h, _POLAR_ITERATIONS), g)
        W = jnp.linalg.solve(h + eye, h - eye)  # tanh(X/2), h = exp(X); |eigenvalues| < tan(π/16)
        W2 = W @ W

        def gregory(i, S):  # Horner for Σ_{k<K} W^{2k}/(2k+1), k = K − 1 − i
            return S @ W2 + eye / (2 * (_GREGORY_TERMS - 1 - i) + 1).astype(dtype)

        S = jnp.broadcast_to(eye / (2 * _GREGORY_TERMS - 1), W.shape)
        S = jax.lax.fori_loop(1, _GREGORY_TERMS, gregory, S)
        y = self.vee(2 * W @ S)  # log h
        x = 2**_ROOTS * y
        if iterations < 1:
            return x

        # First Newton step. dexp(−y) = Σ (−ad_y)ᵏ/(k+1)!, with |ad_y| ≤ π/4.
        A = -self.ad(y)
        eye_d = jnp.eye(self.algebra_dim, dtype=dtype)
        inverse_factorials = jnp.asarray(
            [1 / math.factorial(k + 1) for k in range(_DEXP_TERMS)], dtype=dtype
        )

        def dexp_series(i, D):  # Horner, k = K − 1 − i
            return A @ D + eye_d * inverse_factorials[_DEXP_TERMS - 1 - i]

        D = jnp.broadcast_to(eye_d * inverse_factorials[-1], A.shape)
        D = jax.lax.fori_loop(1, _DEXP_TERMS, dexp_series, D)

        def doubling(_, carry):  # dexp(2z) = ½(I + Ad_{exp z}) dexp(z)
            D, power = carry
            return (D + self.Ad(power) @ D) / 2, power @ power

        # z = −y, −2y, −4y: afterwards D = dexp(−x) and power = exp(−x).
        D, power = jax.lax.fori_loop(0, _ROOTS, doubling, (D, self.inverse(h)))
        residual = self.vee(power @ g)  # log(exp(−x) g) to third order
        x = x + jnp.linalg.solve(D, residual[..., None])[..., 0]
        if iterations < 2:
            return x

        def newton(_, x):
            e = self.inverse(self.exp(x)) @ g
            return x + jnp.einsum("...ab,...b->...a", self.dexpinv(-x), self.vee(e))

        return jax.lax.fori_loop(1, iterations, newton, x)


# `log` takes _ROOTS square roots, each with _POLAR_ITERATIONS scaled Newton iterations for
# the polar factor. The first root must cope with `I + g` nearly singular (angles near π):
# 6 iterations reached round-off for condition numbers up to 1e13 when measured. The later
# ones start from singular values in [cos(π/4), 1] and [cos(π/8), 1] and need 4; the extra
# iterations stay at round-off.
_ROOTS = 3
_POLAR_ITERATIONS = 8
# Terms of the series Σ W^{2k}/(2k+1) with |W| ≤ tan(π/16): the first omitted term is
# below 1e-17 relative.
_GREGORY_TERMS = 12
# Terms of dexp(z) = Σ ad_zᵏ/(k+1)! for |ad_z| ≤ π/4: the first omitted is below 3e-18.
_DEXP_TERMS = 17


def _rotation_sqrt(g, iterations: int):
    """Principal square root of a rotation whose angles are all below π.

    For `g = exp(X)`, `I + g = exp(X/2) · 2cos(X/2)` with `2cos(X/2)` symmetric positive
    definite, so `√g = exp(X/2)` is the orthogonal polar factor of `I + g`. It is computed
    by Newton's iteration `Z ← (γZ + (γZ)⁻ᵀ)/2` with Higham's Frobenius-norm scaling
    `γ = (‖Z⁻¹‖/‖Z‖)^½`, which converges quadratically from any nonsingular start.
    """
    eye = jnp.eye(g.shape[-1], dtype=g.dtype)

    def body(_, Z):
        Z_inv = jnp.linalg.inv(Z)
        gamma = jnp.sqrt(jnp.linalg.norm(Z_inv, axis=(-2, -1)) / jnp.linalg.norm(Z, axis=(-2, -1)))[
            ..., None, None
        ]
        return (gamma * Z + jnp.swapaxes(Z_inv, -1, -2) / gamma) / 2

    return jax.lax.fori_loop(0, iterations, body, g + eye)


@compiled_when_eager
class SOn(AbstractSpecialOrthogonal):
    """The special orthogonal group SO(n), any `n ≥ 2`, in generic matrix form.

    **Arguments:**

    - `n`: matrix size. Algebra coordinates have dimension `n(n−1)/2` (basis in the
      module docstring; `SOn(3)` agrees with [`lievi.SO3`][]).
    """

    n: int = eqx.field(static=True)

    def __check_init__(self):
        if not isinstance(self.n, (int, np.integer)) or self.n < 2:
            raise ValueError(f"SOn: `n` must be an integer ≥ 2, got {self.n!r}.")

    @property
    def matrix_dim(self) -> int:
        return self.n
