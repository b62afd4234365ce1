"""SO(3) in closed form (docs/theory/closed-forms.md), NaN-free in values and gradients.

Every trigonometric coefficient is a function of `θ² = |x|²` with a Taylor branch near
θ = 0. Both branches of a `jnp.where` are differentiated in reverse mode, so the exact
branch is evaluated at a harmless substitute inside the Taylor region ("double where");
otherwise `0 · inf = NaN` leaks into gradients at the identity (jaxlie issue 9,
kornia issue 4404). `log` switches near θ = π to an axis taken from the symmetric part,
where `sin θ` carries no information.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._eager import compiled_when_eager
from ._series import (
    cosc,
    dexpinv_coefficient,
    dot,
    horner,
    outer,
    sinc,
    sinc3,
    small_threshold,
    truncated_dexpinv_terms,
)
from ._son import AbstractSpecialOrthogonal


@compiled_when_eager
class SO3Group(AbstractSpecialOrthogonal):
    """SO(3) with closed forms. Use the instance `lievi.SO3`.

    Coordinates are the usual hat map: `x̂ y = x × y`, identical to `SOn(3)`.
    """

    @property
    def matrix_dim(self) -> int:
        return 3

    def hat(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        if x.shape[-1] != 3:
            raise ValueError(f"so(3) coordinates must have last axis 3, got shape {x.shape}.")
        x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
        z = jnp.zeros_like(x1)
        rows = (
            jnp.stack([z, -x3, x2], axis=-1),
            jnp.stack([x3, z, -x1], axis=-1),
            jnp.stack([-x2, x1, z], axis=-1),
        )
        return jnp.stack(rows, axis=-2)

    def vee(self, X: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
        return (
            jnp.stack(
                [
                    X[..., 2, 1] - X[..., 1, 2],
                    X[..., 0, 2] - X[..., 2, 0],
                    X[..., 1, 0] - X[..., 0, 1],
                ],
                axis=-1,
            )
            / 2
        )

    def bracket(self, x, y):
        return jnp.cross(x, y)

    def ad(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        return self.hat(x)

    def Ad(self, g: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3 3"]:
        return g

    def exp(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        """Rodrigues: `I + (sin θ/θ) x̂ + ((1 − cos θ)/θ²) x̂²`."""
        t2 = dot(x, x)[..., None, None]
        X = self.hat(x)
        return jnp.eye(3, dtype=x.dtype) + sinc(t2) * X + cosc(t2) * (X @ X)

    def log(self, g: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
        """Principal logarithm, `|log g| ≤ π`; accurate up to and at θ = π."""
        dtype = g.dtype
        c = (jnp.trace(g, axis1=-2, axis2=-1) - 1) / 2  # cos θ
        v = self.vee(g)  # sin θ · axis
        vv = dot(v, v)  # sin² θ
        tiny = jnp.finfo(dtype).tiny
        # Near 0 means tan²θ = |v|²/cos²θ below the threshold (and cos θ > 0).
        small = (c > 0) & (vv < small_threshold(dtype) * c * c)
        near_pi = c < 0

        # Away from 0 and π: θ/sin θ · v with θ = atan2(sin θ, cos θ) (no acos of a
        # trace slightly above 3). The square root gets a safe argument where it is unused.
        s = jnp.sqrt(jnp.where(small, 1.0, jnp.maximum(vv, tiny)))
        theta = jnp.arctan2(s, c)
        generic = (theta / s)[..., None] * v

        # Near 0: the same function atan2(s, c)/s = atan(u)/(u c), u = s/c, as a series in
        # u² = vv/c² (u² < 0.1; truncation u¹⁴/15). Being the same function of (v, c) as
        # the generic branch, the derivatives with respect to all nine entries of `g` (not
        # only those along the group) are continuous across the switch.
        c_safe = jnp.where(small, c, 1.0)
        u2 = vv / (c_safe * c_safe)
        series = jnp.zeros_like(u2)
        for k in reversed(range(7)):
            series = series * u2 + (-1) ** k / (2 * k + 1)
        near_zero = (series / c_safe)[..., None] * v

        # Near π: (g + gᵀ)/2 − cos θ I = (1 − cos θ) a aᵀ; read a off its largest column
        # and orient it along v (= sin θ · a).
        B = (g + jnp.swapaxes(g, -1, -2)) / 2 - c[..., None, None] * jnp.eye(3, dtype=dtype)
        diag = jnp.diagonal(B, axis1=-2, axis2=-1)
        k = jnp.argmax(diag, axis=-1)
        column = jnp.take_along_axis(B, k[..., None, None], axis=-1)[..., 0]
        bkk = jnp.take_along_axis(diag, k[..., None], axis=-1)[..., 0]
        denominator = jnp.where(near_pi, bkk * (1 - c), 1.0)
        axis = column / jnp.sqrt(jnp.maximum(denominator, tiny))[..., None]
        orientation = jnp.where(dot(axis, v) < 0, -1.0, 1.0)
        opposite = (orientation * theta)[..., None] * axis

        out = jnp.where(small[..., None], near_zero, generic)
        return jnp.where(near_pi[..., None], opposite, out)

    def dexp(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        """`I + ((1 − cos θ)/θ²) x̂ + ((θ − sin θ)/θ³) x̂²`."""
        t2 = dot(x, x)[..., None, None]
        X = self.hat(x)
        return jnp.eye(3, dtype=x.dtype) + cosc(t2) * X + sinc3(t2) * (X @ X)

    def dexpinv(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        """`I − x̂/2 + (1/θ²)(1 − (θ/2)cot(θ/2)) x̂²` (docs/theory/closed-forms.md)."""
        t2 = dot(x, x)[..., None, None]
        X = self.hat(x)
        return jnp.eye(3, dtype=x.dtype) - X / 2 + dexpinv_coefficient(t2) * (X @ X)

    def dexpinv_series(
        self, x: Float[Array, "*batch 3"], degree: int
    ) -> Float[Array, "*batch 3 3"]:
        """`I − x̂/2 + c(θ²) x̂²`, `c` the polynomial of the series truncated after
        `x̂^degree` (`x̂³ = −θ² x̂`; `_series.truncated_dexpinv_terms`): for `degree = 8`
        (`lievi.RKMK8`'s), `1/12 + θ²/720 + θ⁴/30240 + θ⁶/1209600`."""
        t2 = dot(x, x)[..., None, None]
        X = self.hat(x)
        c = horner(truncated_dexpinv_terms(degree), t2)
        return jnp.eye(3, dtype=x.dtype) - min(degree, 1) * X / 2 + c * (X @ X)

    def cay(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        """`(I − x̂/2)⁻¹(I + x̂/2) = I + 4/(4 + θ²) (x̂ + x̂²/2)`."""
        alpha = (4 / (4 + dot(x, x)))[..., None, None]
        X = self.hat(x)
        return jnp.eye(3, dtype=x.dtype) + alpha * (X + X @ X / 2)

    def cayinv(self, g: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
        """`4 vee(g) / (1 + tr g)`, defined for rotation angles below π."""
        return 4 * self.vee(g) / (1 + jnp.trace(g, axis1=-2, axis2=-1))[..., None]

    def dcay(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        """`4/(4 + θ²) (I + x̂/2)`."""
        alpha = (4 / (4 + dot(x, x)))[..., None, None]
        return alpha * (jnp.eye(3, dtype=x.dtype) + self.hat(x) / 2)

    def dcayinv(self, x: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        """`I − x̂/2 + x xᵀ/4` (docs/theory/closed-forms.md)."""
        return jnp.eye(3, dtype=x.dtype) - self.hat(x) / 2 + outer(x, x) / 4


SO3 = SO3Group()
"""SO(3) with closed-form `exp`, `log`, `dexp`, `dexpinv` and the Cayley maps."""
