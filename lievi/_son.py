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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._group_base import MatrixLieGroup


@functools.lru_cache(maxsize=None)
def _planes(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        i, j, sign = _planes(n)
        if x.shape[-1] != len(i):
            raise ValueError(
                f"so({n}) coordinates must have last axis {len(i)}, got shape {x.shape}."
            )
        signed = x * jnp.asarray(sign, x.dtype)
        X = jnp.zeros(x.shape[:-1] + (n, n), x.dtype)
        return X.at[..., j, i].set(signed).at[..., i, j].set(-signed)

    def vee(self, X: Float[Array, "*batch n n"]) -> Float[Array, "*batch d"]:
        i, j, sign = _planes(self.matrix_dim)
        # The skew part's coordinates: exact on so(n), a projection elsewhere.
        return jnp.asarray(sign, X.dtype) * (X[..., j, i] - X[..., i, j]) / 2

    @property
    def exp_radius(self) -> float:
        # |x| = (Σ θ_i²)^½ over the rotation planes bounds the largest angle θ_i from above.
        return float(jnp.pi)

    def inverse(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
        return jnp.swapaxes(g, -1, -2)

    def membership_defect(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch"]:
        """`‖gᵀg − I‖_F + |det g − 1|` (the determinant term catches reflections)."""
        eye = jnp.eye(self.matrix_dim, dtype=g.dtype)
        orthogonality = jnp.linalg.norm(jnp.swapaxes(g, -1, -2) @ g - eye, axis=(-2, -1))
        return orthogonality + jnp.abs(jnp.linalg.det(g) - 1)

    def log(self, g: Float[Array, "*batch n n"], iterations: int = 8):
        """Principal logarithm for rotation angles below π.

        Starts from the Cayley coordinates `cayinv(g)` (error O(θ³)) and refines with
        Newton's method on `exp(x) = g` in the left trivialisation,
        `x ← x + dexpinv(−x) · vee(exp(−x) g)`, whose derivative at the fixed point is
        the exact derivative of `log`, so it differentiates correctly through the fixed
        number of iterations.
        """

        def body(_, x):
            e = self.inverse(self.exp(x)) @ g
            # vee of the skew part of e is log(e) to third order in log(e).
            return x + jnp.einsum("...ab,...b->...a", self.dexpinv(-x), self.vee(e))

        return jax.lax.fori_loop(0, iterations, body, self.cayinv(g))


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
