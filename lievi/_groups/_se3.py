"""SE(3), the rigid motions of space, in closed form, NaN-free in values and gradients.

Elements are homogeneous 4×4 matrices `g = [[R, p], [0, 1]]` (`R ∈ SO(3)` maps body to
world, `p` is the position of the body origin). Twist coordinates are ordered
**rotation first**, `ξ = (ω, v) ∈ R⁶`, with

    ξ̂ = [[ω̂, v], [0, 0]],

so the first three coordinates are exactly those of `lievi.SO3` (`ω̂ y = ω × y`). For a
left-invariant body `ξ = g⁻¹ġ` is the body angular velocity `ω` and the body-frame
velocity of the origin `v = Rᵀṗ`; the dual momentum `m = (Π, P)` is the body angular
momentum about the body origin and the body linear momentum. (jaxlie orders its tangent
vectors `(v, ω)`; `lievi.to_jaxlie`/`from_jaxlie` convert the group elements.)

Every operator has a block structure over the SO(3) closed forms of `_so3.py`: with
`Ω = ω̂`, `V = v̂` and θ = |ω|,

- `ad_ξ = [[Ω, 0], [V, Ω]]`, `Ad_g = [[R, 0], [p̂R, R]]`;
- `exp ξ = [[exp Ω, J(ω) v], [0, 1]]` with `J = dexp_SO(3)` (the SO(3) right-trivialised
  derivative, the "left Jacobian");
- `dexp(ξ) = [[J, 0], [Q, J]]`, `dexpinv(ξ) = [[J⁻¹, 0], [Q', J⁻¹]]`, where
  `Q = d/dε J(ω + εv)` and `Q' = d/dε J⁻¹(ω + εv)`: since `dexp(ξ) = f(ad_ξ)` for a power
  series `f`, its lower-left block is the Fréchet derivative of `f` at `Ω` in the
  direction `V`, and `f(ω̂) = J(ω)` as a function of `ω`. (In the literature `Q` is written
  out term by term, e.g. Barfoot, *State Estimation for Robotics* (2017), eq. 7.86;
  here its coefficients are the derivatives of the SO(3) ones, taken by forward-mode
  autodiff of the NaN-safe scalar coefficients, so the Taylor branches carry over.)
- Cayley: `cay ξ = [[cay Ω, (I − Ω/2)⁻¹ v], [0, 1]]` and
  `dcayinv(ξ) = [[dcayinv_SO(3)(ω), 0], [−(I − Ω/2)V/2, I − Ω/2]]`.

`exp` is injective for rotation angles `|ω| < π` whatever `v` is; `exp_norm` measures
exactly that.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._base import MatrixLieGroup
from ._eager import compiled_when_eager
from ._series import cosc, dexpinv_coefficient, dot, horner, sinc3, truncated_dexpinv_terms
from ._so3 import SO3


def _split(x):
    return x[..., :3], x[..., 3:]


def _blocks(a, b, c, d):
    """The 6×6 matrix `[[a, b], [c, d]]` from 3×3 blocks (with leading batch axes)."""
    return jnp.concatenate(
        [jnp.concatenate([a, b], axis=-1), jnp.concatenate([c, d], axis=-1)], axis=-2
    )


def _homogeneous(R, p):
    """`[[R, p], [0, 1]]`."""
    batch = R.shape[:-2]
    top = jnp.concatenate([R, p[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.asarray([0, 0, 0, 1], R.dtype), batch + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def _matvec(A, x):
    return jnp.einsum("...ij,...j->...i", A, x)


def _coefficient_and_derivative(coefficient, omega, v):
    """`(c(θ²), d/dε c(|ω + εv|²))` for a scalar SO(3) coefficient `c`, safe at θ = 0.

    Forward mode through the "double where" of `_series_or_exact` differentiates the
    branch that is used (the series near 0), so the derivative is as NaN-free as the value.
    """
    t2 = dot(omega, omega)
    dt2 = 2 * dot(omega, v)
    c, dc = jax.jvp(coefficient, (t2,), (dt2,))
    return c[..., None, None], dc[..., None, None]


@compiled_when_eager
class SE3Group(MatrixLieGroup):
    """SE(3) with closed forms. Use the instance `lievi.SE3`.

    Twist coordinates `ξ = (ω, v)` (rotation first, matching `lievi.SO3`); momentum
    coordinates `m = (Π, P)` dual to them. See the module docstring for the formulas.
    """

    @property
    def matrix_dim(self) -> int:
        return 4

    @property
    def algebra_dim(self) -> int:
        return 6

    # ---- coordinates ----------------------------------------------------------------------

    def hat(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 4 4"]:
        if x.shape[-1] != 6:
            raise ValueError(
                f"se(3) coordinates (ω, v) must have last axis 6, got shape {x.shape}."
            )
        omega, v = _split(x)
        top = jnp.concatenate([SO3.hat(omega), v[..., :, None]], axis=-1)
        bottom = jnp.zeros(x.shape[:-1] + (1, 4), x.dtype)
        return jnp.concatenate([top, bottom], axis=-2)

    def vee(self, X: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 6"]:
        return jnp.concatenate([SO3.vee(X[..., :3, :3]), X[..., :3, 3]], axis=-1)

    def rotation(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 3 3"]:
        """The rotation block `R` of `g = [[R, p], [0, 1]]`."""
        return g[..., :3, :3]

    def translation(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 3"]:
        """The translation `p` of `g = [[R, p], [0, 1]]`."""
        return g[..., :3, 3]

    def from_rotation_translation(
        self, R: Float[Array, "*batch 3 3"], p: Float[Array, "*batch 3"]
    ) -> Float[Array, "*batch 4 4"]:
        """The homogeneous matrix `[[R, p], [0, 1]]`."""
        R, p = jnp.asarray(R), jnp.asarray(p)
        dtype = jnp.result_type(R, p)
        batch = jnp.broadcast_shapes(R.shape[:-2], p.shape[:-1])
        R = jnp.broadcast_to(R.astype(dtype), batch + (3, 3))
        p = jnp.broadcast_to(p.astype(dtype), batch + (3,))
        return _homogeneous(R, p)

    # ---- group structure ------------------------------------------------------------------

    def inverse(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 4 4"]:
        """`[[Rᵀ, −Rᵀp], [0, 1]]`."""
        Rt = jnp.swapaxes(self.rotation(g), -1, -2)
        return _homogeneous(Rt, -_matvec(Rt, self.translation(g)))

    def compose(self, a: Float[Array, "*batch 4 4"], b: Float[Array, "*batch 4 4"]):
        """`ab = [[R_a R_b, R_a p_b + p_a], [0, 1]]`, its rotation block kept orthogonal.

        Each product of rotations in floating point leaves `RᵀR − I` off by an ulp, and
        along a trajectory `g_{k+1} = g_k F_k` these defects add up as a random walk.
        That matters more on SE(3) than on SO(3): the body-frame force of a potential
        invariant under rotations about the origin (central gravity) has a spatial torque
        `Rτ + p × Rf` that vanishes only for orthogonal `R`, so a defect `δ` makes each
        kick inject angular momentum `~ δ·h|p||f|`, the same sign step after step (the
        world-frame defect is nearly constant, the orbit is not), and the total angular
        momentum drifts faster than `√N`. One Newton–Schulz step of the polar
        decomposition, `R ← R(3I − RᵀR)/2`, maps a defect `δ` to `O(δ²)`: on the group
        it is the identity up to round-off, so the map is the same, and the defect stays
        at one rounding instead of accumulating.
        """
        R = SO3.project(self.rotation(a) @ self.rotation(b))
        p = _matvec(self.rotation(a), self.translation(b)) + self.translation(a)
        return _homogeneous(R, p)

    def project(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 4 4"]:
        """The rotation block by `SO3.project`, the last row reset to `(0, 0, 0, 1)`."""
        return _homogeneous(SO3.project(self.rotation(g)), self.translation(g))

    def bracket(self, x, y):
        """`[(ω₁, v₁), (ω₂, v₂)] = (ω₁ × ω₂, ω₁ × v₂ − ω₂ × v₁)`."""
        w1, v1 = _split(x)
        w2, v2 = _split(y)
        return jnp.concatenate([jnp.cross(w1, w2), jnp.cross(w1, v2) - jnp.cross(w2, v1)], -1)

    def ad(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 6 6"]:
        """`[[ω̂, 0], [v̂, ω̂]]`."""
        omega, v = _split(x)
        W = SO3.hat(omega)
        return _blocks(W, jnp.zeros_like(W), SO3.hat(v), W)

    def Ad(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 6 6"]:
        """`[[R, 0], [p̂R, R]]`."""
        R = self.rotation(g)
        return _blocks(R, jnp.zeros_like(R), SO3.hat(self.translation(g)) @ R, R)

    @property
    def exp_radius(self) -> float:
        # exp is injective for rotation angles |ω| < π, whatever the translation.
        return float(jnp.pi)

    def exp_norm(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch"]:
        """The rotation angle `|ω|`, the size `exp_radius` bounds."""
        omega, _ = _split(x)
        return jnp.linalg.norm(omega, axis=-1)

    def membership_defect(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch"]:
        """`‖RᵀR − I‖_F + |det R − 1| + ‖last row − (0, 0, 0, 1)‖`."""
        bottom = g[..., 3, :] - jnp.asarray([0, 0, 0, 1], g.dtype)
        return SO3.membership_defect(self.rotation(g)) + jnp.linalg.norm(bottom, axis=-1)

    def membership_hint(self) -> str:
        return (
            "a rigid motion [[R, p], [0, 1]] has R orthogonal with det R = 1 and last row "
            "(0, 0, 0, 1); build one with lievi.SE3.from_rotation_translation(R, p)"
        )

    # ---- exponential chart ----------------------------------------------------------------

    def exp(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 4 4"]:
        """`[[exp ω̂, J(ω) v], [0, 1]]`."""
        omega, v = _split(x)
        return _homogeneous(SO3.exp(omega), _matvec(SO3.dexp(omega), v))

    def log(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 6"]:
        """Principal logarithm: `ω = log R` (`|ω| ≤ π`), `v = J(ω)⁻¹ p`."""
        omega = SO3.log(self.rotation(g))
        v = _matvec(SO3.dexpinv(omega), self.translation(g))
        return jnp.concatenate([omega, v], axis=-1)

    def dexp(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 6 6"]:
        """`Σ ad_ξⁿ/(n+1)! = [[J, 0], [Q, J]]`, `J = I + a Ω + b Ω²`, `Q = ∂_v J`."""
        omega, v = _split(x)
        W, V = SO3.hat(omega), SO3.hat(v)
        a, da = _coefficient_and_derivative(cosc, omega, v)  # (1 − cos θ)/θ²
        b, db = _coefficient_and_derivative(sinc3, omega, v)  # (θ − sin θ)/θ³
        W2 = W @ W
        J = jnp.eye(3, dtype=x.dtype) + a * W + b * W2
        Q = da * W + a * V + db * W2 + b * (W @ V + V @ W)
        return _blocks(J, jnp.zeros_like(J), Q, J)

    def dexpinv(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 6 6"]:
        """Inverse of `dexp`: `[[J⁻¹, 0], [∂_v J⁻¹, J⁻¹]]`, `J⁻¹ = I − Ω/2 + c Ω²`."""
        omega, v = _split(x)
        W, V = SO3.hat(omega), SO3.hat(v)
        c, dc = _coefficient_and_derivative(dexpinv_coefficient, omega, v)
        Jinv = jnp.eye(3, dtype=x.dtype) - W / 2 + c * (W @ W)
        Qinv = -V / 2 + dc * (W @ W) + c * (W @ V + V @ W)
        return _blocks(Jinv, jnp.zeros_like(Jinv), Qinv, Jinv)

    def dexpinv_transpose_apply(self, x, mu):
        """`dexpinv(x)ᵀ μ` by cross products: `(Jᵀa + Qᵀb, Jᵀb)` for `μ = (a, b)`, with
        `Jᵀy = y + ω×y/2 + c ω×(ω×y)` and `Qᵀb = v×b/2 + c' ω×(ω×b) + c (v×(ω×b) + ω×(v×b))`.
        Under `jax.vmap` the `6×6` matrix and its product were most of RATTLE's residual
        on the chains of docs/articulated.md."""
        omega, v = _split(x)
        a, b = _split(mu)
        c, dc = _coefficient_and_derivative(dexpinv_coefficient, omega, v)
        c, dc = c[..., 0], dc[..., 0]

        def jt(y):
            return y + jnp.cross(omega, y) / 2 + c * jnp.cross(omega, jnp.cross(omega, y))

        wb = jnp.cross(omega, b)
        qt = (
            jnp.cross(v, b) / 2
            + dc * jnp.cross(omega, wb)
            + c * (jnp.cross(v, wb) + jnp.cross(omega, jnp.cross(v, b)))
        )
        return jnp.concatenate([jt(a) + qt, jt(b)], axis=-1)

    def dexpinv_series(
        self, x: Float[Array, "*batch 6"], degree: int
    ) -> Float[Array, "*batch 6 6"]:
        """`dexpinv`'s series truncated after `ad_x^degree`: `dexpinv`'s blocks with `c` the
        SO(3) polynomial (`SO3.dexpinv_series`). Exact, since `ad_ξᵏ = [[Ωᵏ, 0], [∂_v Ωᵏ, Ωᵏ]]`:
        the lower-left block of the sum is `∂_v` of the upper-left one."""
        omega, v = _split(x)
        W, V = SO3.hat(omega), SO3.hat(v)
        terms = truncated_dexpinv_terms(degree)
        c, dc = _coefficient_and_derivative(lambda t: horner(terms, t), omega, v)
        half = min(degree, 1) / 2
        Jinv = jnp.eye(3, dtype=x.dtype) - half * W + c * (W @ W)
        Qinv = -half * V + dc * (W @ W) + c * (W @ V + V @ W)
        return _blocks(Jinv, jnp.zeros_like(Jinv), Qinv, Jinv)

    # ---- Cayley chart (paper §5) ------------------------------------------------------------

    def cay(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 4 4"]:
        """`(I − ξ̂/2)⁻¹(I + ξ̂/2) = [[cay Ω, (I − Ω/2)⁻¹ v], [0, 1]]`,
        with `(I − Ω/2)⁻¹ = (I + cay Ω)/2`."""
        omega, v = _split(x)
        C = SO3.cay(omega)
        return _homogeneous(C, _matvec(C + jnp.eye(3, dtype=x.dtype), v) / 2)

    def cayinv(self, g: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 6"]:
        """`ω = cayinv R`, `v = (I − ω̂/2) p`; rotation angles below π."""
        omega = SO3.cayinv(self.rotation(g))
        p = self.translation(g)
        return jnp.concatenate([omega, p - jnp.cross(omega, p) / 2], axis=-1)

    def dcay(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 6 6"]:
        """`[[D, 0], [v̂D/2, (I + cay Ω)/2]]` with `D = dcay_SO(3)(ω)`."""
        omega, v = _split(x)
        D = SO3.dcay(omega)
        E = (SO3.cay(omega) + jnp.eye(3, dtype=x.dtype)) / 2
        return _blocks(D, jnp.zeros_like(D), SO3.hat(v) @ D / 2, E)

    def dcayinv(self, x: Float[Array, "*batch 6"]) -> Float[Array, "*batch 6 6"]:
        """`y ↦ (I − ξ̂/2) ŷ (I + ξ̂/2)`: `[[dcayinv_SO(3)(ω), 0], [−(I − Ω/2)V/2, I − Ω/2]]`."""
        omega, v = _split(x)
        A = jnp.eye(3, dtype=x.dtype) - SO3.hat(omega) / 2
        D = SO3.dcayinv(omega)
        return _blocks(D, jnp.zeros_like(D), -A @ SO3.hat(v) / 2, A)

    # ---- Lie–Poisson structure --------------------------------------------------------------

    def casimirs(self, m: Float[Array, "*batch 6"]) -> Float[Array, "*batch 2"]:
        """The Casimirs of `se(3)*` at `m = (Π, P)`: `(|P|², P·Π)` (Kirchhoff's equations)."""
        Pi, P = _split(m)
        return jnp.stack([dot(P, P), dot(P, Pi)], axis=-1)


SE3 = SE3Group()
"""SE(3) with closed-form `exp`, `log`, `dexp`, `dexpinv` and the Cayley maps; twists `(ω, v)`."""
