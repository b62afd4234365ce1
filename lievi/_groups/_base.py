"""The abstract matrix Lie group: everything derived from `hat` and `vee`.

A concrete group supplies the matrix size `n`, the algebra dimension `d` and the
isomorphism `hat: R^d -> g ⊂ gl(n)` with its inverse `vee`. From these the base class
derives the operators the discrete Euler–Poincaré equations need (paper §4.1):

- `ad(x)`: the matrix of `y ↦ [x, y]` in the algebra coordinates;
- `Ad(g)`: the matrix of `y ↦ g y g⁻¹`;
- `dexp(x) = Σ ad_xⁿ/(n+1)!`, the right-trivialised derivative of `exp`
  (`d exp(x + εy)/dε · exp(−x) = dexp(x) y`), which is the paper's `iex(ad_x)` (4.3);
- `dexpinv(x) = dexp(x)⁻¹`, the paper's `χ(−ad_x)`, and `dexpinv_series(x, degree)`, its
  commutator series `Σ B_k/k! ad_xᵏ` truncated after `ad_x^degree`;
- the Cayley map `cay(x) = (I − x/2)⁻¹(I + x/2)` (paper §5) with its
  right-trivialised derivative `dcay` and inverse `dcayinv`.

Every method accepts leading batch axes. Subclasses override methods with closed forms
where they have them (see `SO3Group`); the generic versions here are the reference the
closed forms are tested against.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._expm import expm, phi1
from ._series import bernoulli_terms


class MatrixLieGroup(eqx.Module):
    """A matrix Lie group `G ⊂ GL(n)` with Lie algebra coordinates in `R^d`.

    Subclasses implement `matrix_dim`, `algebra_dim`, `hat`, `vee` and `log`. All other
    methods have generic implementations built from those.
    """

    # ---- what a concrete group must supply -------------------------------------------

    @property
    @abc.abstractmethod
    def matrix_dim(self) -> int:
        """`n`, the size of the matrices."""

    @property
    @abc.abstractmethod
    def algebra_dim(self) -> int:
        """`d = dim g`, the number of algebra coordinates."""

    @abc.abstractmethod
    def hat(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch n n"]:
        """Algebra coordinates `x ∈ R^d` to the matrix `x̂ ∈ g`."""

    @abc.abstractmethod
    def vee(self, X: Float[Array, "*batch n n"]) -> Float[Array, "*batch d"]:
        """Inverse of `hat` (on matrices outside `g`, the coordinates of a projection)."""

    @abc.abstractmethod
    def log(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch d"]:
        """Principal logarithm: algebra coordinates `x` with `exp(x) = g`."""

    # ---- group structure ----------------------------------------------------------------

    def identity(self, dtype=float) -> Float[Array, "n n"]:
        return jnp.eye(self.matrix_dim, dtype=dtype)

    def compose(self, a: Float[Array, "*batch n n"], b: Float[Array, "*batch n n"]):
        return a @ b

    def rotation(self, g: Float[Array, "*batch n n"]):
        """The rotation part of `g` (its attitude), or `None` where the group has none
        (the default)."""
        return None

    def translation(self, g: Float[Array, "*batch n n"]):
        """The translation part of `g` (its position), or `None` where the group has none
        (the default)."""
        return None

    def inverse(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
        return jnp.linalg.inv(g)

    def project(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
        """`g` moved back onto the group where round-off has moved it off (a defect `δ`
        becomes `O(δ²)`; on the group the identity up to round-off). Default: `g`."""
        return g

    def basis(self, dtype=float) -> Float[Array, "d n n"]:
        """The basis matrices `E_a = hat(e_a)`, stacked."""
        return self.hat(jnp.eye(self.algebra_dim, dtype=dtype))

    def bracket(self, x: Float[Array, "*batch d"], y: Float[Array, "*batch d"]):
        """Lie bracket `[x, y] = vee(x̂ŷ − ŷx̂)`."""
        X, Y = self.hat(x), self.hat(y)
        return self.vee(X @ Y - Y @ X)

    def _columns(self, M: Float[Array, "*batch d n n"]) -> Float[Array, "*batch d d"]:
        # M[..., a] is the image of the basis matrix E_a; vee it and make it column a.
        return jnp.swapaxes(self.vee(M), -1, -2)

    def ad(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch d d"]:
        """Matrix of `ad_x: y ↦ [x, y]`."""
        X = self.hat(x)[..., None, :, :]
        E = self.basis(x.dtype)
        return self._columns(X @ E - E @ X)

    def Ad(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch d d"]:
        """Matrix of `Ad_g: y ↦ vee(g ŷ g⁻¹)`."""
        G = g[..., None, :, :]
        Ginv = self.inverse(g)[..., None, :, :]
        return self._columns(G @ self.basis(g.dtype) @ Ginv)

    # ---- exponential chart --------------------------------------------------------------

    def exp(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch n n"]:
        return expm(self.hat(x))

    def dexp(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch d d"]:
        """`Σ ad_xⁿ/(n+1)!`, the right-trivialised derivative of `exp` (paper's `iex`)."""
        return phi1(self.ad(x))

    def dexpinv(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch d d"]:
        """Inverse of `dexp(x)`; the paper's `χ(−ad_x)` (see (4.8))."""
        D = self.dexp(x)
        eye = jnp.broadcast_to(jnp.eye(self.algebra_dim, dtype=D.dtype), D.shape)
        return jnp.linalg.solve(D, eye)

    def dexpinv_transpose_apply(self, x, mu):
        """`dexp⁻¹(x)ᵀ μ`, the chart's factor of a DEP momentum `dexp⁻¹(ξ)ᵀ M ξ / h`;
        groups with a closed form apply it without building the matrix."""
        return jnp.einsum("...ji,...j->...i", self.dexpinv(x), mu)

    def dexpinv_series(
        self, x: Float[Array, "*batch d"], degree: int
    ) -> Float[Array, "*batch d d"]:
        """`Σ_{k ≤ degree} B_k/k! ad_xᵏ`: `dexpinv(x)`'s commutator series truncated after
        `ad_x^degree` (`B_k` the Bernoulli numbers, `B_1 = −1/2`). A Lie-group Runge–Kutta
        method of order `p` keeps its order with `degree ≥ p − 1` (`lievi.RKMK8`: 8), since
        `ad_uᵏ = O(hᵏ)` in the chart (Munthe-Kaas; Hairer–Lubich–Wanner, §IV.8.2)."""
        terms = bernoulli_terms(degree)
        A = self.ad(x)
        eye = jnp.broadcast_to(jnp.eye(self.algebra_dim, dtype=A.dtype), A.shape)
        value = terms[degree] * eye
        for c in reversed(terms[:degree]):
            value = A @ value + c * eye
        return value

    # ---- Cayley chart (paper §5) -------------------------------------------------------------

    def _half(self, x):
        X = self.hat(x)
        eye = jnp.eye(self.matrix_dim, dtype=X.dtype)
        return eye - X / 2, eye + X / 2

    def cay(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch n n"]:
        """Cayley map `(I − x̂/2)⁻¹(I + x̂/2)`."""
        minus, plus = self._half(x)
        return jnp.linalg.solve(minus, plus)

    def cayinv(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch d"]:
        """Inverse Cayley map `2 (g + I)⁻¹ (g − I)`."""
        eye = jnp.eye(self.matrix_dim, dtype=g.dtype)
        return self.vee(2 * jnp.linalg.solve(g + eye, g - eye))

    def dcay(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch d d"]:
        """Right-trivialised derivative of `cay`: `y ↦ (I − x̂/2)⁻¹ ŷ (I + x̂/2)⁻¹`."""
        minus, plus = self._half(x)
        minus_inv = jnp.linalg.inv(minus)[..., None, :, :]
        plus_inv = jnp.linalg.inv(plus)[..., None, :, :]
        return self._columns(minus_inv @ self.basis(x.dtype) @ plus_inv)

    def dcayinv(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch d d"]:
        """Inverse of `dcay`: `y ↦ (I − x̂/2) ŷ (I + x̂/2) = y − [x, y]/2 − x̂ŷx̂/4`."""
        minus, plus = self._half(x)
        return self._columns(minus[..., None, :, :] @ self.basis(x.dtype) @ plus[..., None, :, :])

    @property
    def exp_radius(self) -> float:
        """`exp` is injective on `{x : |x| < exp_radius}` (∞ if unknown)."""
        return float("inf")

    def exp_norm(self, x: Float[Array, "*batch d"]) -> Float[Array, "*batch"]:
        """The size of `x` that `exp_radius` bounds (default: the Euclidean norm)."""
        return jnp.linalg.norm(x, axis=-1)

    # ---- Lie–Poisson structure -------------------------------------------------------------

    def casimirs(self, m: Float[Array, "*batch d"]) -> Float[Array, "*batch k"]:
        """Casimir functions of the Lie–Poisson structure on `g*` at `m`, where known."""
        raise NotImplementedError(f"casimirs are not implemented for {type(self).__name__}.")

    # ---- checks ---------------------------------------------------------------------------

    def membership_defect(self, g: Float[Array, "*batch n n"]) -> Float[Array, "*batch"]:
        """How far `g` is from the group (0 on the group). Generic groups: 0."""
        return jnp.zeros(g.shape[:-2], g.dtype)

    def membership_hint(self) -> str:
        """What a group element is and how to make one, for error messages."""
        return "pass an element of the group"
