"""Any reduced Lagrangian `l: g → R` on any matrix Lie group (paper §2–§4)."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
from jaxtyping import Array, Float, Scalar

from .._groups._base import MatrixLieGroup
from ._base import AbstractLieSystem
from ._potential import AbstractPotential, as_potential
from ._side import Side


class LieLagrangian(AbstractLieSystem):
    """A system given by its reduced Lagrangian; derivatives by autodiff.

    **Arguments:**

    - `group`: a `MatrixLieGroup`, e.g. `lievi.SO3` or `lievi.SOn(5)`.
    - `l`: the reduced Lagrangian, a function of algebra coordinates `(d,) → ()`. It must
      be strictly convex near the motion (regular Legendre map).
    - `side`: `"left"` for a left-invariant system (`ξ = g⁻¹ġ`), `"right"` for a
      right-invariant one (`ξ = ġg⁻¹`).
    - `potential`: `None`, a `lievi.AbstractPotential` or a callable `V(g)`; the
      Lagrangian is then `l(ξ) − V(g)` (paper §7).
    """

    group: MatrixLieGroup = eqx.field(static=True)
    side: Side = eqx.field(static=True)
    l: Callable[[Float[Array, " d"]], Scalar]
    potential: AbstractPotential | None

    def __init__(self, group: MatrixLieGroup, l: Callable, side: str = "left", potential=None):
        self.group = group
        self.l = l
        self.side = _as_side(side)
        self.potential = as_potential(potential)

    def __check_init__(self):
        if not callable(self.l):
            raise ValueError(f"`l` must be a callable reduced Lagrangian ξ ↦ l(ξ), got {self.l!r}.")
        if not isinstance(self.group, MatrixLieGroup):
            raise ValueError(f"`group` must be a lievi MatrixLieGroup, got {type(self.group)}.")

    def lagrangian(self, xi: Float[Array, " d"]) -> Scalar:
        return self.l(xi)


def _as_side(side) -> Side:
    """`Side` from `"left"`/`"right"` (or a `Side`), with an error naming the argument."""
    try:
        return Side(side)
    except ValueError:
        sides = tuple(s.value for s in Side)
        raise ValueError(f"`side` must be one of {sides}, got {side!r}.") from None
