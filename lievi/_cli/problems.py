"""The demo's test problems: the systems, their initial states, their conserved
quantities, and the integrators that apply; the control problem's data and closed form.

`free-body`: the free rigid body of Hairer, Lubich & Wanner, *Geometric Numerical
Integration*, §VII.5 (`I = (2, 1, 2/3)`, `Π₀ = (cos 1.1, 0, sin 1.1)`, `g₀ = I₃`, `h = 0.1`,
`T = 100`). `heavy-top`: an asymmetric heavy top with an off-axis centre of mass (the same
inertia, `m γ = 1`, `ρ = (0.3, −0.2, 0.5)`, a tilted `g₀`), the paper's §7. `control`:
rest-to-rest reorientation by 150° about `a = (1, 2, 2)/3` in `T = 2` (see `control`).
`binary`: a binary asteroid, two bodies of three point masses in mutual gravity on
SE(3)² (`lievi.gravitating_bodies`).

Adding an integrator to the demo is one row in `INTEGRATORS`; a problem is one `Problem`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

import lievi
from lievi import diagnostics

# (display name, integrator): one row each in the table and the plot.
INTEGRATORS: tuple[tuple[str, lievi.AbstractIntegrator], ...] = (
    ("DEP exp chart", lievi.DEP(chart="exp")),
    ("DEP Cayley chart", lievi.DEP(chart="cayley")),
    ("Moser–Veselov", lievi.MoserVeselov()),
    ("Lie–Poisson splitting", lievi.LiePoissonSplitting()),
    ("RK4 (non-geometric)", lievi.RK4()),
    ("Composition(MV), order 6", lievi.Composition(lievi.MoserVeselov(), order=6)),
    ("preprocessed DMV, order 6", lievi.PreprocessedMoserVeselov(order=6)),
)

# The HLW problem (Hairer, Lubich & Wanner, §VII.5).
INERTIA = (2.0, 1.0, 2.0 / 3.0)
THETA = 1.1
DEFAULT_H = 0.1
DEFAULT_STEPS = 1000  # T = 100 at h = 0.1
REFERENCE_TOL = 1e-13


def hlw_problem():
    """`(body, g0, m0)` of the Hairer–Lubich–Wanner rigid body."""
    body = lievi.RigidBody(jnp.array(INERTIA))
    m0 = jnp.array([math.cos(THETA), 0.0, math.sin(THETA)])
    return body, jnp.eye(3), m0


# The asymmetric heavy top: the HLW inertia about the fixed point, an off-axis centre of
# mass, nondimensional gravity, tilted initial attitude (the paper's §7).
CENTER_OF_MASS = (0.3, -0.2, 0.5)
TILT = (0.4, -0.3, 0.2)  # g₀ = exp(TILT^)


def heavy_top_problem():
    """`(top, g0, m0)` of the asymmetric heavy top."""
    top = lievi.heavy_top(jnp.array(INERTIA), 1.0, jnp.array(CENTER_OF_MASS), gravity=1.0)
    m0 = jnp.array([math.cos(THETA), 0.0, math.sin(THETA)])
    return top, lievi.SO3.exp(jnp.array(TILT)), m0


def _free_body_invariants(system, g, m):
    """The free body's Casimir |Π|² and spatial angular momentum gΠ."""
    return {
        "casimir_drift": diagnostics.relative_drift(diagnostics.casimirs(system, m)),
        "spatial_momentum_drift": diagnostics.relative_drift(
            diagnostics.spatial_momentum(system, g, m)
        ),
    }


def _heavy_top_invariants(system, g, m):
    """The heavy top's Casimirs of the reduced (Π, Γ) dynamics, Γ = gᵀe₃ the vertical in
    the body: |Γ|² (= 1) and Π·Γ = e₃·(gΠ), the vertical angular momentum."""
    gamma = g[:, 2, :]
    return {
        "gamma_norm_defect": jnp.max(jnp.abs(jnp.sum(gamma**2, axis=1) - 1)),
        "vertical_momentum_drift": diagnostics.relative_drift(jnp.sum(m * gamma, axis=1)),
    }


# The binary asteroid: two bodies of three point masses each (G = 1) on a near-circular
# mutual orbit at distance BINARY_DISTANCE, spinning about generic axes.
BINARY_MASSES = ((1.0, 0.6, 0.8), (0.5, 0.4, 0.3))
BINARY_POINTS = (
    ((0.12, 0.0, 0.0), (-0.1, 0.08, 0.0), (0.0, -0.06, 0.09)),
    ((0.1, 0.0, 0.02), (-0.08, 0.07, 0.0), (0.0, -0.05, -0.08)),
)
BINARY_DISTANCE = 1.5
BINARY_SPIN = ((0.3, 0.5, 1.0), (1.0, -0.5, 0.2))
BINARY_TILT = ((0.0, 0.0, 0.0), (0.3, -0.2, 0.5))


def binary_problem():
    """`(bodies, g0, m0)` of the binary asteroid: the barycentre at rest at the origin,
    the relative velocity of a circular orbit of the two total masses."""
    bodies = lievi.gravitating_bodies(1.0, jnp.array(BINARY_MASSES), jnp.array(BINARY_POINTS))
    mass = bodies.mass
    total = jnp.sum(mass)
    x = BINARY_DISTANCE * jnp.array([-mass[1], mass[0]]) / total
    speed = jnp.sqrt(total / BINARY_DISTANCE)
    velocity = speed * jnp.array([[0.0, -mass[1], 0.0], [0.0, mass[0], 0.0]]) / total
    R = lievi.SO3.exp(jnp.array(BINARY_TILT))
    g0 = lievi.SE3.from_rotation_translation(R, jnp.stack([x, 0 * x, 0 * x], axis=1))
    P = jnp.einsum("nji,nj->ni", R, mass[:, None] * velocity)  # body frame
    Pi = jnp.einsum("nij,nj->ni", bodies.tensor[:, :3, :3], jnp.array(BINARY_SPIN))
    return bodies, g0, jnp.concatenate([Pi, P], axis=1)


def _binary_invariants(system, g, m):
    """The total linear and angular momentum (the diagonal symmetry's momentum map)."""
    total = diagnostics.total_momentum(system, g, m)
    return {
        "angular_momentum_drift": diagnostics.relative_drift(total[:, :3]),
        "linear_momentum_change": jnp.max(jnp.abs(total[:, 3:] - total[0, 3:])),
    }


class Problem(NamedTuple):
    """A demo problem: the system and state, defaults, the integrators that apply, and
    its conserved quantities (table columns `(key, header 1, header 2, format)`)."""

    title: str
    description: tuple[str, ...]
    make: Callable
    default_h: float
    default_steps: int
    integrators: tuple
    invariants: Callable
    columns: tuple
    legend: str
    json: dict
    # Appended to the plot's title.
    plot_note: str = ", I = (2, 1, 2/3)"


PROBLEMS = {
    "free-body": Problem(
        title="free rigid body on SO(3), Hairer–Lubich–Wanner test problem",
        description=("inertia I = (2, 1, 2/3),  Π₀ = (cos 1.1, 0, sin 1.1),  g₀ = I₃",),
        make=hlw_problem,
        default_h=DEFAULT_H,
        default_steps=DEFAULT_STEPS,
        integrators=INTEGRATORS,
        invariants=_free_body_invariants,
        columns=(
            ("casimir_drift", "rel. drift", "Casimir", "{:.2e}"),
            ("spatial_momentum_drift", "rel. drift", "spat.mom", "{:.2e}"),
        ),
        legend="the Casimir |Π|², and the spatial momentum gΠ",
        json={
            "name": "Hairer–Lubich–Wanner rigid body",
            "inertia": list(INERTIA),
            "m0": [math.cos(THETA), 0.0, math.sin(THETA)],
            "g0": "identity",
        },
    ),
    "heavy-top": Problem(
        title="asymmetric heavy top on SO(3) (uniform gravity, off-axis centre of mass)",
        description=(
            "inertia I = (2, 1, 2/3) about the fixed point,  m γ = 1,  ρ = (0.3, −0.2, 0.5)",
            "Π₀ = (cos 1.1, 0, sin 1.1),  g₀ = exp((0.4, −0.3, 0.2)^)",
        ),
        make=heavy_top_problem,
        default_h=DEFAULT_H,
        default_steps=DEFAULT_STEPS,
        # The preprocessed DMV is a free-body method (its modified inertia has no potential).
        integrators=tuple(
            (n, i) for n, i in INTEGRATORS if not isinstance(i, lievi.PreprocessedMoserVeselov)
        ),
        invariants=_heavy_top_invariants,
        columns=(
            ("gamma_norm_defect", "Casimirs", "max||Γ|²−1|", "{:.2e}"),
            ("vertical_momentum_drift", "Casimirs", "Π·Γ drift", "{:.2e}"),
        ),
        legend=(
            "the Casimirs of the heavy top,\n  |Γ|² (max deviation from 1) and Π·Γ = e₃·(gΠ) "
            "(relative drift), Γ = gᵀe₃ the vertical in the body"
        ),
        json={
            "name": "asymmetric heavy top",
            "inertia": list(INERTIA),
            "mass_times_gravity": 1.0,
            "center_of_mass": list(CENTER_OF_MASS),
            "m0": [math.cos(THETA), 0.0, math.sin(THETA)],
            "g0": {"rotation_vector": list(TILT)},
        },
    ),
    "binary": Problem(
        title="binary asteroid on SE(3)² (two bodies of three point masses, mutual gravity)",
        description=(
            "masses (1, 0.6, 0.8) and (0.5, 0.4, 0.3), G = 1, distance 1.5, circular orbit",
            "spins ω₁ = (0.3, 0.5, 1), ω₂ = (1, −0.5, 0.2); the plot shows body 1's Π",
        ),
        make=binary_problem,
        default_h=0.01,
        default_steps=2000,
        # The methods that step each body of `lievi.RigidBodies` (Moser–Veselov too; it has
        # no discrete Lagrangian on SE(3)ᴺ for the DEL column, so it is left out here).
        integrators=(
            ("DEP exp chart", lievi.DEP(chart="exp")),
            ("DEP Cayley chart", lievi.DEP(chart="cayley")),
            ("Lie–Poisson splitting", lievi.LiePoissonSplitting()),
            ("RK4 (non-geometric)", lievi.RK4()),
            ("Composition(split.), order 4", lievi.Composition(lievi.LiePoissonSplitting(), 4)),
        ),
        invariants=_binary_invariants,
        columns=(
            ("angular_momentum_drift", "total ang.", "rel. drift", "{:.2e}"),
            ("linear_momentum_change", "total lin.", "max change", "{:.2e}"),
        ),
        legend=(
            "the total angular momentum Σ RΠ + p × RP (relative drift) and the total "
            "linear momentum Σ RP (max change; it is 0)"
        ),
        json={
            "name": "binary asteroid",
            "masses": [list(m) for m in BINARY_MASSES],
            "points": [[list(p) for p in body] for body in BINARY_POINTS],
            "distance": BINARY_DISTANCE,
            "spin": [list(w) for w in BINARY_SPIN],
        },
        plot_note=", body 1",
    ),
}
DEFAULT_PROBLEM = "free-body"
CONTROL_PROBLEM = "control"

# The control problem: rest-to-rest reorientation by CONTROL_THETA about CONTROL_AXIS in
# the fixed time CONTROL_T.
CONTROL_THETA = 5 * np.pi / 6  # 150°
CONTROL_AXIS = jnp.array([1.0, 2.0, 2.0]) / 3
CONTROL_T = 2.0
SPACECRAFT_INERTIA = (1.0, 2.0, 3.0)
CONTROL_DEFAULT_STEPS = 60  # the spacecraft's N
SPHERE_STEPS = (16, 32)


def control_target():
    """`(g_f, m_f)`: at rest at `exp(θ a^)`."""
    return lievi.SO3.exp(CONTROL_THETA * CONTROL_AXIS), jnp.zeros(3)


def closed_form_control(j, n):
    """The spherical body's (`J = jI`) optimal `u(t)` at the step midpoints, (n, 3):
    `u(t) = (j θ_f / T²)(6 − 12 t/T) a` (see `control`)."""
    s = (np.arange(n) + 0.5) / n
    return (j * CONTROL_THETA / CONTROL_T**2 * (6 - 12 * s))[:, None] * np.asarray(CONTROL_AXIS)


def closed_form_cost(j):
    """The spherical body's optimal cost `J* = ∫|u|² dt = 12 j² θ_f² / T³`."""
    return 12 * j**2 * CONTROL_THETA**2 / CONTROL_T**3
