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
`largest_omega_h` the largest step it was fitted on (no larger step is suggested), and
`seconds_per_body_step` its measured cost (one core, float64, the batch of the
benchmark). Regenerate `TABLE` with

    python benchmarks/work_precision.py --knowledge

which runs the classes below and prints the table to paste here (`--knowledge-from FILES`
fits it from results files instead: the Lagrange top's entries come from its full-size
runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp

from ._groups._so3 import SO3
from ._integrators._composition import Composition
from ._integrators._rkmk import RKMK4, RKMK5, RKMK8
from ._integrators._splitting import LiePoissonSplitting
from ._integrators._symmetric_top import SymmetricTopSplitting
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
    "symmetric top RKN 4": lambda: SymmetricTopSplitting(4),
    "symmetric top RKN 6": lambda: SymmetricTopSplitting(6),
}

# Two near-exact runs of the benchmark's asymmetric heavy top agree on the invariants to
# 1e-13 and part by O(1) rad in attitude by t ≈ 8000 (ω ≈ 1.5): a divergence rate of about
# ln(1e13)/8000 per unit time, `LYAPUNOV_PER_FREQUENCY · ω`. Trajectory errors of any
# method then grow like ε·exp(λt) from round-off ε (`ROUNDOFF`).
LYAPUNOV_PER_FREQUENCY = math.log(1e13) / 8000 / 1.5
ROUNDOFF = 1e-15

# Where each class of `TABLE` was measured: its costs are this machine's, its ranking within
# a class is what carries over.
_QUICK_RUN = (
    "python benchmarks/work_precision.py --knowledge --quick --problems 'free body' 'heavy top' "
    "--methods splitting 'splitting ∘ 4' 'splitting ∘ 6' 'splitting ∘ 8' RKMK8; 2026-11-29, "
    "shared 2-core x86-64, load average 11, batch 64, T = 20 and 200, one core"
)
MEASURED = {
    "free body": _QUICK_RUN,
    "heavy top": _QUICK_RUN,
    "Lagrange top": (
        "python benchmarks/work_precision.py --knowledge-from "
        "benchmarks/results/work_precision_lagrange_top_{short,long}.json (the full-size "
        "runs: 2026-11-30, 2-core x86-64, load 1.8, batch 256, T = 20 and 2·10⁴, one core)"
    ),
}
# (class, method) → order, seconds per body-step, {quantity: (C, a, floor)} (module
# docstring); the attitude only on the integrable classes (the heavy top's is chaotic).
TABLE: dict[tuple[str, str], dict] = {
    ("free body", "RKMK8"): {
        "order": 8,
        "seconds_per_body_step": 2.2999318750005493e-07,
        "largest_omega_h": 0.6394662129388805,
        "errors": {
            "attitude": (1.8248821187723346e-10, 1.075, 1.7420377170709948e-12),
            "energy": (7.389022059945657e-13, 0.971, 3.502425820873472e-15),
            "momentum": (4.222479389327716e-09, -0.001, 4.563763585907479e-13),
        },
    },
    ("free body", "splitting"): {
        "order": 2,
        "seconds_per_body_step": 1.1332432031252449e-07,
        "largest_omega_h": 0.6394662129388805,
        "errors": {
            "attitude": (0.004760877703356801, 1.0, 0.0),
            "energy": (0.017960222513880426, 0.001, 0.0),
            "momentum": (0.0, 0.0, 5.744106420370108e-15),
        },
    },
    ("free body", "splitting ∘ 4"): {
        "order": 4,
        "seconds_per_body_step": 3.3805285937482667e-07,
        "largest_omega_h": 0.6394662129388805,
        "errors": {
            "attitude": (0.00790999574113855, 1.036, 0.0),
            "energy": (0.0008058624416455854, -0.0, 0.0),
            "momentum": (0.0, 0.0, 8.770732690117704e-15),
        },
    },
    ("free body", "splitting ∘ 6"): {
        "order": 6,
        "seconds_per_body_step": 8.848443750000267e-07,
        "largest_omega_h": 0.6394662129388805,
        "errors": {
            "attitude": (1.5582640096346327e-05, 0.985, 0.0),
            "energy": (2.922656341209634e-06, 0.0, 0.0),
            "momentum": (0.0, 0.0, 1.6128554416203867e-14),
        },
    },
    ("free body", "splitting ∘ 8"): {
        "order": 8,
        "seconds_per_body_step": 1.2187589921874852e-06,
        "largest_omega_h": 0.6394662129388805,
        "errors": {
            "attitude": (4.033601815351286e-09, 0.878, 0.0),
            "energy": (5.0227125253254884e-09, -0.072, 3.772851715070318e-13),
            "momentum": (0.0, 0.0, 1.9670622421778463e-14),
        },
    },
    ("heavy top", "RKMK8"): {
        "order": 8,
        "seconds_per_body_step": 3.6215380468740396e-07,
        "largest_omega_h": 0.2803312426547308,
        "errors": {
            "energy": (5.256954647317967e-10, 1.0, 2.180064183572884e-15),
            "momentum": (1.4529167906569987e-09, 1.0, 3.0450266701328224e-15),
        },
    },
    ("heavy top", "splitting"): {
        "order": 2,
        "seconds_per_body_step": 1.1590125000005002e-07,
        "largest_omega_h": 0.2803312426547308,
        "errors": {
            "energy": (0.06176161153403682, -0.078, 0.0),
            "momentum": (0.0, 0.0, 4.905876301880658e-15),
        },
    },
    ("heavy top", "splitting ∘ 4"): {
        "order": 4,
        "seconds_per_body_step": 3.247490703126576e-07,
        "largest_omega_h": 0.2803312426547308,
        "errors": {
            "energy": (0.010508066674629977, 0.072, 0.0),
            "momentum": (0.0, 0.0, 8.057257067767987e-15),
        },
    },
    ("heavy top", "splitting ∘ 6"): {
        "order": 6,
        "seconds_per_body_step": 7.54130187500035e-07,
        "largest_omega_h": 0.2803312426547308,
        "errors": {
            "energy": (2.539479604056074e-05, 0.028, 0.0),
            "momentum": (0.0, 0.0, 1.6070974092367672e-14),
        },
    },
    ("heavy top", "splitting ∘ 8"): {
        "order": 8,
        "seconds_per_body_step": 1.6543334765626305e-06,
        "largest_omega_h": 0.2803312426547308,
        "errors": {
            "energy": (3.5954620958413856e-07, 0.008, 4.609278559554098e-14),
            "momentum": (0.0, 0.0, 1.9530465938036126e-14),
        },
    },
    # The symmetric top: its own class (integrable, and `SymmetricTopSplitting` applies).
    ("Lagrange top", "RKMK8"): {
        "order": 8,
        "seconds_per_body_step": 1.8762671535156316e-07,
        "largest_omega_h": 1.6740343968328149,
        "errors": {
            "attitude": (1.518481406312756e-07, 1.695, 1.2248870471893228e-12),
            "energy": (3.12180875734023e-10, 0.952, 3.606202393004296e-16),
            "momentum": (1.4616955955627723e-09, 0.951, 1.0493833073405092e-15),
        },
    },
    ("Lagrange top", "symmetric top RKN 4"): {
        "order": 4,
        "seconds_per_body_step": 1.4793923258300783e-07,
        "largest_omega_h": 1.6740343968328149,
        "errors": {
            "attitude": (6.472180902297129e-08, 0.975, 9.027865992672331e-12),
            "energy": (2.0248361793343423e-08, 0.028, 1.6844027145295676e-13),
            "momentum": (0.0, 0.0, 8.945990603805272e-14),
        },
    },
    ("Lagrange top", "symmetric top RKN 6"): {
        "order": 6,
        "seconds_per_body_step": 2.62428246425781e-07,
        "largest_omega_h": 1.6740343968328149,
        "errors": {
            "attitude": (7.523446144111595e-08, 1.106, 1.2490102800435184e-12),
            "energy": (8.199804789522712e-11, -0.0, 1.4424809572017184e-15),
            "momentum": (0.0, 0.0, 8.307695252347412e-14),
        },
    },
}


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
    Lagrange top (`I₁ = I₂`, centre of mass on the symmetry axis: integrable) or any other
    heavy top (taken as chaotic, as the benchmark's asymmetric top is: the integrable
    Kovalevskaya case is not singled out), or `None` where the table knows nothing of it (other
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
    if strength == 0:  # no torque: a free body
        return ProblemClass("free body", False, speed)
    frequency = max(speed, math.sqrt(strength / min(moments)))
    symmetric = moments[0] == moments[1] and float(b[0]) == 0.0 and float(b[1]) == 0.0
    return ProblemClass("Lagrange top" if symmetric else "heavy top", not symmetric, frequency)


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
