"""The side of a system's symmetry: left- or right-invariant (paper §2).

A left-invariant system (the rigid body) has the body velocity `ξ = g⁻¹ġ` and momentum `Π`;
its increment acts on the right, `g_{k+1} = g_k F_k` (2.9). A right-invariant system has
the spatial velocity `ξ = ġg⁻¹` and momentum `μ`; `g_{k+1} = F_k g_k` (2.8). The two are
mirror images under `g ↦ g⁻¹`. `Side` owns every formula that differs between them, so no
other code asks which side it is on. A `str` enumeration: `system.side == "left"` works.
"""

from __future__ import annotations

import enum

import jax.numpy as jnp


class Side(str, enum.Enum):
    """`Side.LEFT` (`"left"`) or `Side.RIGHT` (`"right"`)."""

    LEFT = "left"
    RIGHT = "right"

    def __str__(self) -> str:
        return self.value

    @property
    def sign(self) -> int:
        """`+1` (left) or `−1` (right): the sign of `ξ` in `dφ⁻¹(±ξ)` of the DEP equation."""
        return 1 if self is Side.LEFT else -1

    def translate(self, g, F):
        """`g F` (left) or `F g` (right): `g` moved by an increment (or a perturbation)."""
        return g @ F if self is Side.LEFT else F @ g

    def compose(self, group, g, F):
        """`translate` by the group's product (`MatrixLieGroup.compose`, which may keep the
        result on the group to round-off)."""
        return group.compose(g, F) if self is Side.LEFT else group.compose(F, g)

    def increment(self, group, g0, g1):
        """The increment from `g0` to `g1`: `g0⁻¹g1` (left) or `g1g0⁻¹` (right)."""
        return group.inverse(g0) @ g1 if self is Side.LEFT else g1 @ group.inverse(g0)

    def momentum_after(self, group, F, m):
        """The discrete Lie–Poisson update (3.3)/(3.2): `Ad_Fᵀ m` (left) or `Ad_{F⁻¹}ᵀ m`."""
        A = group.Ad(F) if self is Side.LEFT else group.Ad(group.inverse(F))
        return A.T @ m

    def tangent(self, group, g, xi):
        """`ġ` of the velocity `ξ`: `g ξ̂` (left) or `ξ̂ g` (right)."""
        return self.translate(g, group.hat(xi))

    def coadjoint_sign(self) -> int:
        """The sign of the Euler–Poincaré equation `ṁ = ± ad_ξᵀ m` (2.4)/(2.5)."""
        return self.sign

    def noether_momentum(self, group, g, m):
        """The momentum conserved by the symmetry: `Ad_{g⁻¹}ᵀ Π` (left: the spatial
        momentum, `gΠ` on SO(3)) or `Ad_gᵀ μ` (right: the body momentum)."""
        A = group.Ad(group.inverse(g)) if self is Side.LEFT else group.Ad(g)
        return jnp.einsum("...ba,...b->...a", A, m)

    def other_frame(self, group, g, xi):
        """The velocity in the other frame: `Ad_g ξ` (left: body → spatial) or
        `Ad_{g⁻¹} ξ` (right: spatial → body)."""
        A = group.Ad(g if self is Side.LEFT else group.inverse(g))
        return jnp.einsum("...ab,...b->...a", A, xi)

    def carried_frame(self) -> str:
        """The frame of the velocity this side carries: `"body"` or `"spatial"`."""
        return "body" if self is Side.LEFT else "spatial"
