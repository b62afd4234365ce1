"""`suggest_integrator`: the method and step that reach a target accuracy most cheaply —
from the work–precision benchmark's knowledge where it has measured the kind of problem
(`_suggest_knowledge.py`: the free rigid body, the heavy and the Lagrange top; no run at
all), else from a short pilot run (the work–precision diagram, for the user's own problem).

**Pilot.** Its cost is bounded to a fraction `pilot_fraction` of the run it predicts
(compilation apart): it integrates a window `T_p = max(pilot_fraction·T/7, 8h₀)` (at most
`T`), so that its `n + 2n + 4n = 7n` steps of each candidate cost at most that fraction of
the run's `T/h₀` steps of one body (the run's own step is at most `h₀`, its batch at least
one body). The errors at the end of the window are extrapolated to the horizon by their
growth law: trajectory errors grow like `t` for a symmetric method (linear phase error)
and `t²` otherwise; the energy's and the momentum map's are bounded for a symmetric
method and grow like `t` otherwise (Hairer–Lubich–Wanner, *Geometric Numerical
Integration*, §X.3, §XI.3).

For each candidate of order `p` the pilot integrates the user's initial state over the
window at three steps `h₀, h₀/2, h₀/4` and compares a final quantity `q(T)` — the
element `g` (the default), its attitude or position, the momentum `m`, or the energy (the
`tolerance_on` argument of `suggest_integrator`). With `d₁ = ‖q_{h₀} − q_{h₀/2}‖`,
`d₂ = ‖q_{h₀/2} − q_{h₀/4}‖` (the Euclidean/Frobenius norm over every body at the end of
the horizon), the observed order is `log₂(d₁/d₂)`; the order used, `q`, is the smaller of it
and `p` (where the pilot is not yet asymptotic this predicts a smaller step, never a
larger one), and Richardson's estimate of the error at `h₀/4` is `d₂/(2^q − 1)`. The step
that meets `tolerance` is then `h = (h₀/4)·(tolerance/error)^{1/q}`, capped at `h₀` (no
extrapolation beyond the pilot), and rounded down to divide the horizon. The cost of a
candidate is its measured time per body-step on `simulate_batch`'s path (a batch of
copies of the state, after compilation) times the steps it needs.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ._checks import check_integer, check_scalar
from ._integrators._composition import Composition
from ._integrators._dep import DEP
from ._integrators._rkmk import RKMK4, RKMK5, RKMK8
from ._results import RESULTS
from ._save import Save
from ._simulate_batch import simulate_batch
from ._suggest_knowledge import (
    MEASURED,
    METHODS,
    TABLE,
    largest_step,
    predicted_error,
    problem_class,
)
from .diagnostics import energy, spatial_momentum


def _attitudes(system, g, m):
    return system.group.rotation(g)


def _positions(system, g, m):
    return system.group.translation(g)


def _momentum_map(system, g, m):
    """The conserved part of the Noether momentum: all of it for a free system; in a
    potential of advected direction `a` (gravity), its component along `a` (the symmetry
    left is the rotations about `a`)."""
    J = spatial_momentum(system, g, m)
    a = None if system.potential is None else system.potential.advected_direction()
    if a is None:
        return J
    a = jnp.asarray(a, J.dtype)[..., : J.shape[-1]]
    return (J @ a / jnp.linalg.norm(a))[..., None]


# What `tolerance_on` names: the final quantity whose error the pilot estimates, from the
# final state `(g, m)` of one run (one row per body for a system of several). `None`
# where the system's group has no such part (a position on SO(3)).
MEASURES = {
    "g": lambda system, g, m: g,
    "attitude": _attitudes,
    "position": _positions,
    "momentum": lambda system, g, m: m,
    "energy": lambda system, g, m: energy(system, g, m),
    "momentum map": _momentum_map,
}
# Growth of each quantity's error with the horizon, `t^a`, for a symmetric method and for
# another (module docstring).
GROWTH = {
    "g": (1, 2),
    "attitude": (1, 2),
    "position": (1, 2),
    "momentum": (1, 2),
    "energy": (0, 1),
    "momentum map": (0, 1),
}
TRAJECTORY = ("g", "attitude", "position", "momentum")


def default_candidates():
    """Methods that apply to every system: DEP and its compositions of order 4, 6 and 8,
    and the Lie-group Runge–Kutta methods of order 4, 5 and 8."""
    return (
        DEP(),
        Composition(DEP(), 4),
        Composition(DEP(), 6),
        Composition(DEP(), 8),
        RKMK4(),
        RKMK5(),
        RKMK8(),
    )


@dataclass(frozen=True)
class Suggestion:
    """What `suggest_integrator` found.

    **Attributes:**

    - `integrator`: the cheapest candidate that reaches the tolerance.
    - `h`, `n_steps`: its step (dividing the horizon) and the number of steps.
    - `predicted_error`: the pilot's estimate of the final error at that step, in the
      quantity `suggest_integrator`'s `tolerance_on` names (`g` by default).
    - `seconds_per_body`: the predicted cost of one body's run on this machine
      (`simulate_batch`'s path, measured on the pilot batch).
    - `table`: one row per candidate (`name`, `order`, `h`, `n_steps`, `predicted_error`,
      `seconds_per_body`; a pilot's also `observed_order`, or `failed` with its message).
    - `source`: `"knowledge"` (the benchmark's table, no run) or `"pilot"`.
    """

    integrator: object
    h: float
    n_steps: int
    predicted_error: float
    seconds_per_body: float
    table: list[dict] = field(default_factory=list)
    source: str = "pilot"


def suggest_integrator(
    system,
    g0,
    m0,
    *,
    horizon,
    tolerance,
    candidates=None,
    h0=None,
    batch: int = 256,
    tolerance_on: str = "g",
    pilot_fraction: float = 0.1,
) -> Suggestion:
    """The method and step `h` that reach a final error `tolerance` over `horizon` at the
    least cost: from the benchmark's knowledge where it has measured this kind of problem
    and `candidates` is not given, else from a pilot run of each candidate (module
    docstring).

    **Arguments:**

    - `system`, `g0`, `m0`: one initial state, as for `lievi.simulate` (one body, or one
      state of a system of several bodies such as `lievi.RigidBodies`: `g0` `(N, 4, 4)`,
      `m0` `(N, 6)`).
    - `horizon`: the length of the run `T > 0`.
    - `tolerance`: the target error `> 0` at the end of the run in the quantity
      `tolerance_on` names.
    - `tolerance_on`: which final quantity `tolerance` bounds, over every body at once:
      `"g"` (the default: the element, `‖g_h(T) − g(T)‖_F`; on SE(3) this mixes the
      rotation and the position, in the position's units), `"attitude"` (the rotation part
      only, `‖R_h(T) − R(T)‖_F`, dimensionless), `"position"` (the translation only,
      `‖p_h(T) − p(T)‖`, on SE(3)), `"momentum"` (the momentum coordinates,
      `‖m_h(T) − m(T)‖`), `"energy"` (the total energy `|E_h(T) − E(T)|`,
      `lievi.diagnostics.energy`) or `"momentum map"` (the conserved part of
      `lievi.diagnostics.spatial_momentum`: all of it for a free body, its vertical
      component in gravity).
    - `candidates`: integrators to compare by a pilot run. By default: for a problem the
      benchmark knows (one rigid body on SO(3) with principal moments, free or in uniform
      gravity; `tolerance_on` `"g"`, `"attitude"`, `"energy"` or `"momentum map"`) the
      methods of its table, without any run; else `DEP()`, its compositions of order 4, 6,
      8, and `RKMK4()`, `RKMK5()`, `RKMK8()` by a pilot. Each needs `order()`.
    - `h0`: the pilot's largest step (default: the step that turns `0.4` rad at the
      initial angular speed — of the fastest body, for several — at most `horizon/8`).
    - `batch`: the bodies in the pilot's timing run.
    - `pilot_fraction`: the pilot's cost bound, as a fraction of the predicted run's (module
      docstring); `0 < pilot_fraction`. A larger fraction integrates a longer window and
      extrapolates less.

    **Returns:** a `Suggestion`. Raises `ValueError` if no candidate's pilot succeeds, or if
    the problem is chaotic and `tolerance` bounds a trajectory quantity beyond the
    predictability horizon (no method can meet it there: errors of round-off at the start
    have grown past the tolerance; bound the energy or the momentum map instead).
    """
    check_scalar("horizon", horizon, positive=True)
    check_scalar("tolerance", tolerance, positive=True)
    check_scalar("pilot_fraction", pilot_fraction, positive=True)
    batch = check_integer("batch", batch, 1)
    horizon, tolerance = float(horizon), float(tolerance)
    system.check_element("g0", g0)
    system.check_momentum("m0", m0)
    g0, m0 = jnp.asarray(g0), jnp.asarray(m0)
    measure = _measure(system, tolerance_on, g0, m0)
    known = problem_class(system, g0, m0)
    if known is not None and tolerance_on in TRAJECTORY:
        reachable = known.predictability_horizon(tolerance)
        if horizon > reachable:
            raise ValueError(
                f"`horizon={horizon:g}`: this {known.name} is chaotic, and a trajectory "
                f"target (`tolerance_on={tolerance_on!r}`, `tolerance={tolerance:g}`) cannot "
                f"be met beyond its predictability horizon, about {reachable:.3g} here "
                "(round-off errors at the start grow past the tolerance for every method). "
                "Bound an invariant instead (`tolerance_on='energy'` or 'momentum map'), or "
                "shorten the horizon."
            )
    if candidates is None and known is not None and tolerance_on in KNOWN_QUANTITIES:
        suggestion = _from_knowledge(system, known, horizon, tolerance, tolerance_on, g0, m0)
        if suggestion is not None:
            return suggestion
    if h0 is None:
        # The fastest body's angular speed (one value per body for a system of several).
        speed = float(jnp.max(system.group.exp_norm(system.velocity(m0))))
        h0 = min(horizon / 8, 0.4 / speed) if speed > 0 else horizon / 8
    check_scalar("h0", h0, positive=True)
    candidates = default_candidates() if candidates is None else tuple(candidates)
    # The window: 7n steps a candidate at most `pilot_fraction` of the run's T/h₀ steps,
    # and at least 8 steps of h₀ for the errors to be asymptotic.
    window = min(horizon, max(pilot_fraction * horizon / 7, 8 * float(h0)))
    rows, best = [], None
    for integrator in candidates:
        row = _pilot(
            system, integrator, g0, m0, horizon, window, tolerance, float(h0), batch, measure
        )
        if "failed" not in row:
            growth = GROWTH[tolerance_on][0 if integrator.is_symmetric() else 1]
            row = _extrapolated(row, (horizon / window) ** growth, tolerance, horizon)
        rows.append(row)
        if "failed" not in row and (best is None or row["seconds_per_body"] < best[1]):
            best = (integrator, row["seconds_per_body"], row)
    if best is None:
        raise ValueError(
            "no candidate's pilot run succeeded: "
            + "; ".join(f"{r['name']}: {r['failed']}" for r in rows)
            + ". Pass a smaller `h0`."
        )
    integrator, seconds, row = best
    return Suggestion(integrator, row["h"], row["n_steps"], row["predicted_error"], seconds, rows)


# The quantities of the table: `tolerance_on` ↦ (the benchmark's quantity, its scale from
# the initial state: the benchmark's energy and momentum errors are relative).
KNOWN_QUANTITIES = {
    # ‖R_h − R‖_F = 2√2 sin(θ/2) ≈ √2 θ for the rotation angle θ between them.
    "g": ("attitude", lambda system, g0, m0: math.sqrt(2.0)),
    "attitude": ("attitude", lambda system, g0, m0: math.sqrt(2.0)),
    "energy": ("energy", lambda system, g0, m0: abs(float(energy(system, g0, m0)))),
    "momentum map": ("momentum", lambda system, g0, m0: float(jnp.linalg.norm(m0))),
}


def _from_knowledge(system, known, horizon, tolerance, tolerance_on, g0, m0):
    """The cheapest method of the table for this class, with its largest step meeting the
    tolerance; `None` where the table has nothing for the class."""
    quantity, scale = KNOWN_QUANTITIES[tolerance_on]
    target = tolerance / scale(system, g0, m0)
    omega, rows, best = known.frequency, [], None
    for (name, method), entry in TABLE.items():
        if name != known.name or quantity not in entry["errors"]:
            continue
        integrator = METHODS[method]()
        # Within the method's stability bound, the steps the table was fitted on, and the
        # horizon.
        h_max = min(horizon, integrator.step_bound() / omega, entry["largest_omega_h"] / omega)
        h = min(largest_step(entry, quantity, omega, horizon, target), h_max)
        if h <= 0:
            rows.append({"name": method, "order": entry["order"], "failed": "floor above target"})
            continue
        n_steps = max(1, math.ceil(horizon / h))
        h = horizon / n_steps
        error = predicted_error(entry, quantity, omega, h, horizon) * scale(system, g0, m0)
        row = {
            "name": method,
            "order": entry["order"],
            "h": h,
            "n_steps": n_steps,
            "predicted_error": error,
            "seconds_per_body": entry["seconds_per_body_step"] * n_steps,
            "measured": MEASURED[known.name],
        }
        rows.append(row)
        if best is None or row["seconds_per_body"] < best[1]["seconds_per_body"]:
            best = (integrator, row)
    if best is None:
        return None
    integrator, row = best
    return Suggestion(
        integrator,
        row["h"],
        row["n_steps"],
        row["predicted_error"],
        row["seconds_per_body"],
        rows,
        source="knowledge",
    )


def _extrapolated(row, factor, tolerance, horizon):
    """The pilot's row at the window's end carried to the horizon: errors times `factor`
    (the growth law), and the step shrunk by `factor^(1/q)` to meet the tolerance."""
    q = min(max(row["observed_order"], 1.0), float(row["order"]))
    error = row["predicted_error"] * factor
    if error <= tolerance:
        return {**row, "predicted_error": error}
    h = row["h"] * (tolerance / error) ** (1.0 / q)
    n_steps = max(1, math.ceil(horizon / h))
    h_new = horizon / n_steps
    return {
        **row,
        "h": h_new,
        "n_steps": n_steps,
        "predicted_error": error * (h_new / row["h"]) ** q,
        "seconds_per_body": row["seconds_per_body"] / row["n_steps"] * n_steps,
    }


def _measure(system, tolerance_on, g0, m0):
    """The function of the final state that `tolerance_on` names (`MEASURES`), checked to
    apply to `system`."""
    if tolerance_on not in MEASURES:
        raise ValueError(
            f"`tolerance_on` must be one of {', '.join(map(repr, MEASURES))}, got {tolerance_on!r}."
        )
    measure = MEASURES[tolerance_on]
    if jax.eval_shape(lambda g, m: measure(system, g, m), g0, m0) is None:
        raise ValueError(
            f"`tolerance_on={tolerance_on!r}`: the elements of {type(system.group).__name__} "
            "have no such part; use 'g' (the whole element) or 'attitude'."
        )
    return measure


def _pilot(system, integrator, g0, m0, horizon, window, tolerance, h0, batch, measure):
    """The pilot over `window` (module docstring): the step meeting `tolerance` at the
    window's end, and the run's steps and cost over `horizon` at that step."""
    order = integrator.order()
    row = {"name": f"{type(integrator).__name__} (order {order})", "order": order}
    # The pilot's steps: the largest dividing the window at most h₀, then its halves.
    n0 = max(1, math.ceil(window / h0))
    finals = []
    for level in range(3):
        solution = _final(
            system, integrator, g0[None], m0[None], window / (n0 * 2**level), n0 * 2**level
        )
        code = int(solution.result[0])
        if code != RESULTS.successful:
            row["failed"] = RESULTS.messages[code]
            return row
        final = measure(system, solution.g[0, -1], solution.m[0, -1])
        finals.append(np.asarray(final, float))
    d1 = float(np.linalg.norm(finals[0] - finals[1]))
    d2 = float(np.linalg.norm(finals[1] - finals[2]))
    observed = math.log2(d1 / d2) if d1 > 0 and d2 > 0 else float(order)
    q = min(max(observed, 1.0), float(order))
    h_fine, h_cap = window / (4 * n0), window / n0
    error = d2 / (2.0**q - 1.0)  # Richardson, at h_fine
    h = h_fine * (tolerance / error) ** (1.0 / q) if error > 0 else h_cap
    n_steps = max(1, math.ceil(horizon / min(h, h_cap)))
    h = horizon / n_steps
    # The cost: time per body-step of a batch of copies, after compilation.
    gs, ms = jnp.broadcast_to(g0, (batch, *g0.shape)), jnp.broadcast_to(m0, (batch, *m0.shape))
    steps = min(4 * n0, 64)
    jax.block_until_ready(_final(system, integrator, gs, ms, h, steps))
    start = time.perf_counter()
    jax.block_until_ready(_final(system, integrator, gs, ms, h, steps))
    per_body_step = (time.perf_counter() - start) / (batch * steps)
    row.update(
        observed_order=observed,
        h=h,
        n_steps=n_steps,
        predicted_error=error * (h / h_fine) ** q,
        seconds_per_body=per_body_step * n_steps,
    )
    return row


def _final(system, integrator, g0, m0, h, n_steps):
    final = Save(g=True, m=True, stats=False, every=n_steps)
    return simulate_batch(system, integrator, g0, m0, h=h, n_steps=n_steps, save=final, throw=False)
