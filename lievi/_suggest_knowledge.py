"""What `suggest_integrator` knows without a pilot run: error constants and costs from the
work–precision benchmark, for the problem classes it measured.

For a known class, method and quantity the final error of a run of step `h` to the horizon
`T` is modelled as

    error ≈ C · (ωh)^p · (ωT)^a + floor,

`p` the method's order, `ω` the problem's frequency scale (`frequency`), `a` the growth
with the horizon (about 1 for the attitude of a symmetric method: linear phase error; 0
for its energy: bounded; larger for the non-symmetric `RKMK`, whose energy drifts), and
`floor` the round-off level (an invariant the method keeps: the momentum map of a
structure-preserving method). `C`, `a` and `floor` are fitted to the benchmark's errors
(largest over its bodies and its saved times, so over `t ≤ T`) at both of its horizons;
`seconds_per_body_step` is its measured cost (one core, float64, the batch of the
benchmark). Regenerate `TABLE` with

    python benchmarks/work_precision.py --knowledge

which runs the classes below and prints the table to paste here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp

from ._groups._so3 import SO3
from ._integrators._composition import Composition
from ._integrators._rkmk import RKMK4, RKMK5, RKMK8
from ._integrators._splitting import LiePoissonSplitting
from ._kernels._kick import rigid_body_coupling

# The methods of the table, by the benchmark's names.
METHODS = {
    "splitting": LiePoissonSplitting,
    "splitting ∘ 4": lambda: Composition(LiePoissonSplitting(), 4),
    "splitting ∘ 6": lambda: Composition(LiePoissonSplitting(), 6),
    "splitting ∘ 8": lambda: Composition(LiePoissonSplitting(), 8),
    "RKMK4": RKMK4,
    "RKMK5": RKMK5,
    "RKMK8": RKMK8,
}

# Two near-exact runs of the benchmark's asymmetric heavy top agree on the invariants to
# 1e-13 and part by O(1) rad in attitude by t ≈ 8000 (ω ≈ 1.5): a divergence rate of about
# ln(1e13)/8000 per unit time, `LYAPUNOV_PER_FREQUENCY · ω`. Trajectory errors of any
# method then grow like ε·exp(λt) from round-off ε (`ROUNDOFF`).
LYAPUNOV_PER_FREQUENCY = math.log(1e13) / 8000 / 1.5
ROUNDOFF = 1e-15

# (class, method) → order, seconds per body-step, {quantity: (C, a, floor)}; filled by
# `benchmarks/work_precision.py --knowledge`.
TABLE: dict[tuple[str, str], dict] = {}
MEASURED = "(not measured)"


@dataclass(frozen=True)
class ProblemClass:
    """A class of problems the table knows: its name, whether it is chaotic, and its
    frequency scale `ω` for one state."""

    name: str
    chaotic: bool
    frequency: float

    def predictability_horizon(self, tolerance: float) -> float:
        """The time after which an error of round-off at the start has grown past
        `tolerance`, `ln(tolerance/ε)/λ` (infinite for a non-chaotic class)."""
        if not self.chaotic:
            return math.inf
        rate = LYAPUNOV_PER_FREQUENCY * self.frequency
        return math.log(max(tolerance, ROUNDOFF) / ROUNDOFF) / rate


def problem_class(system, g0, m0) -> ProblemClass | None:
    """The class of `system` (one body on SO(3), principal moments): the free rigid body, the
    Lagrange top (`I₁ = I₂`, centre of mass on the symmetry axis: integrable) or the
    asymmetric heavy top (chaotic), or `None` where the table knows nothing of it (other
    groups, several bodies, other potentials: `suggest_integrator` then runs a pilot)."""
    tensor = system.kinetic_tensor()
    if system.group != SO3 or tensor is None or jnp.shape(tensor) != (3,) or jnp.ndim(m0) != 1:
        return None
    moments = [float(x) for x in tensor]
    speed = math.sqrt(sum((float(p) / i) ** 2 for p, i in zip(m0, moments)))
    if system.potential is None:
        return ProblemClass("free body", False, speed)
    if not rigid_body_coupling(system.potential):
        return None
    a, b = system.potential.linear_coupling()
    strength = float(jnp.linalg.norm(a) * jnp.linalg.norm(b))
    frequency = max(speed, math.sqrt(strength / min(moments)))
    symmetric = moments[0] == moments[1] and float(b[0]) == 0.0 and float(b[1]) == 0.0
    return ProblemClass("heavy top", not symmetric, frequency)


def predicted_error(entry, quantity: str, omega: float, h: float, horizon: float):
    """`C (ωh)^p (ωT)^a + floor` for a table entry, or `None` where it has no such
    quantity."""
    if quantity not in entry["errors"]:
        return None
    C, a, floor = entry["errors"][quantity]
    return C * (omega * h) ** entry["order"] * (omega * horizon) ** a + floor


def largest_step(entry, quantity: str, omega: float, horizon: float, tolerance: float):
    """The largest `h` whose `predicted_error` is at most `tolerance` (`inf` where every
    step is, `0` where none is: the floor is above the tolerance)."""
    C, a, floor = entry["errors"][quantity]
    room = tolerance - floor
    if room <= 0:
        return 0.0
    if C == 0:
        return math.inf
    return (room / (C * (omega * horizon) ** a)) ** (1 / entry["order"]) / omega
