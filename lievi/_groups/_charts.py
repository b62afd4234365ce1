"""Charts of a matrix Lie group: the map `φ: g → G` that writes a step's increment
`F_k = φ(ξ_k)` in algebra coordinates (paper §4, (4.7); the Cayley variant after (5.7)).

A chart owns what differs between the exponential and the Cayley map: `φ`, `φ⁻¹`, the
inverse of its right-trivialised derivative `dφ⁻¹` (the operator of the DEP equation
(4.8)), and its branch rule — which roots of the DEP equation lie on the branch continued
from `h → 0`. Integrators and kernels ask the chart; nothing else compares chart names.
Charts compare equal to their names (`DEP().chart == "exp"`), the public shorthand.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp


class AbstractChart(eqx.Module):
    """A chart `φ` of a matrix Lie group, near the identity."""

    name: ClassVar[str]
    # `c₂` with `dφ⁻¹(ξ) = 1 − ½ ad_ξ + c₂ ad_ξ² + O(|ξ|³)` where the chart's second-order
    # term is a multiple of `ad_ξ²`, else 0 (its first-order part only): RATTLE's momentum
    # blocks in closed form (`_integrators/_rattle_blocks.py`) read it.
    ad_squared: ClassVar[float] = 0.0

    @abc.abstractmethod
    def map(self, group, xi):
        """`φ(ξ)`."""

    @abc.abstractmethod
    def inverse(self, group, F):
        """`φ⁻¹(F)`."""

    @abc.abstractmethod
    def dinverse(self, group, xi):
        """`dφ⁻¹(ξ)`, the inverse of the right-trivialised derivative of `φ` at `ξ`."""

    def dinverse_transpose_apply(self, group, xi, mu):
        """`dφ⁻¹(ξ)ᵀ μ` (a DEP momentum's chart factor); charts with a closed form skip
        the matrix."""
        return jnp.einsum("...ji,...j->...i", self.dinverse(group, xi), mu)

    @abc.abstractmethod
    def beyond_branch(self, angle_squared, radius: float):
        """Whether an increment turning by `√angle_squared` is past the chart's branch
        (`radius`: the group's `exp_radius`, π on SO(n) and for SE(3)'s rotation).
        Traceable; the one branch rule of the one-body and batched paths."""

    def __eq__(self, other):
        if isinstance(other, str):
            return other == self.name
        return type(self) is type(other)

    def __hash__(self):
        return hash(self.name)

    def __str__(self) -> str:
        return self.name

    def __repr__(self) -> str:
        return repr(self.name)


class ExpChart(AbstractChart):
    """The exponential map (the paper's (4.7)–(4.8))."""

    name: ClassVar[str] = "exp"
    ad_squared: ClassVar[float] = 1 / 12  # dexp⁻¹ = Σ B_k ad^k / k!, B₂ = 1/6

    def map(self, group, xi):
        return group.exp(xi)

    def inverse(self, group, F):
        return group.log(F)

    def dinverse(self, group, xi):
        return group.dexpinv(xi)

    def dinverse_transpose_apply(self, group, xi, mu):
        return group.dexpinv_transpose_apply(xi, mu)

    def beyond_branch(self, angle_squared, radius: float):
        # Beyond the injectivity radius of exp the "root" belongs to another branch of log:
        # the step is meaningless.
        return angle_squared >= radius**2


class CayleyChart(AbstractChart):
    """The Cayley map `cay(ξ) = (1 − ξ̂/2)⁻¹(1 + ξ̂/2)` (the variant after (5.7))."""

    name: ClassVar[str] = "cayley"
    # `dcay⁻¹(ξ) y = y − ½[ξ, y] − ¼ ξ̂ ŷ ξ̂`: the last term is not a multiple of `ad_ξ² y`.
    ad_squared: ClassVar[float] = 0.0

    def map(self, group, xi):
        return group.cay(xi)

    def inverse(self, group, F):
        return group.cayinv(F)

    def dinverse(self, group, xi):
        return group.dcayinv(xi)

    def beyond_branch(self, angle_squared, radius: float):
        # `cay` is a diffeomorphism onto the elements without a half-turn: one branch.
        return jnp.zeros(jnp.shape(angle_squared), bool)


CHARTS = {chart.name: chart for chart in (ExpChart(), CayleyChart())}


def as_chart(chart) -> AbstractChart:
    """A chart from its name (`"exp"`, `"cayley"`) or itself; `ValueError` otherwise."""
    if isinstance(chart, AbstractChart):
        return chart
    if isinstance(chart, str) and chart in CHARTS:
        return CHARTS[chart]
    raise ValueError(f"`chart` must be one of {tuple(CHARTS)}, got {chart!r}.")
