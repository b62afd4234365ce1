"""Splitting schemes `(a, b)`: the weights of a kick – drift – … – kick step.

A symmetric splitting of `H = T + V` into a free part `T` (the "drift", the free rigid
body's flow) and a potential `V` (the "kick", the flow of its torque) takes, for a step `h`,

    e^{b_s h V} ∘ e^{a_s h T} ∘ … ∘ e^{b_1 h V} ∘ e^{a_1 h T} ∘ e^{b_0 h V}

(kick first: the "BAB" form), with `s` drift weights `a_i` and `s + 1` kick weights `b_i`,
`Σa_i = Σb_i = 1`. Adjacent steps share a kick (`b_s` of one and `b_0` of the next act at
the same configuration), so a run evaluates the torque `s` times a step.

A symmetric composition `Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}` of the Strang step kick – drift – kick
(`lievi.Composition` of a kick integrator) is the special case `a_i = γ_i`,
`b_0 = γ_1/2`, `b_i = (γ_i + γ_{i+1})/2`, `b_s = γ_s/2` (`from_composition`): the kick
weights follow from the drift weights. Runge–Kutta–Nyström splittings choose them
independently (`lievi.SymmetricTopSplitting`).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class SplittingScheme:
    """Drift weights `a_1 … a_s` and kick weights `b_0 … b_s` (module docstring)."""

    drifts: tuple[float, ...]
    kicks: tuple[float, ...]

    def __post_init__(self):
        if len(self.kicks) != len(self.drifts) + 1:
            raise ValueError(
                f"a splitting scheme needs one kick weight more than drift weights, got "
                f"{len(self.drifts)} drifts and {len(self.kicks)} kicks."
            )

    @classmethod
    def from_composition(cls, coefficients: tuple[float, ...]) -> SplittingScheme:
        """The composition of kick – drift – kick at the stages `γ_i h`, adjacent half
        kicks merged."""
        halves = [gamma / 2 for gamma in coefficients]
        middle = [a + b for a, b in zip(halves, halves[1:])]
        return cls(tuple(coefficients), (halves[0], *middle, halves[-1]))
