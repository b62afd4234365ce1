"""`suggest_integrator`: the method and step that reach a target accuracy most cheaply,
from a short pilot run (the work–precision diagram, for the user's own problem).

For each candidate of order `p` the pilot integrates the user's initial state over the
whole horizon at three steps `h₀, h₀/2, h₀/4` and compares a final quantity `q(T)` — the
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
from .diagnostics import energy


def _attitudes(system, g, m):
    return system.group.rotation(g)


def _positions(system, g, m):
    return system.group.translation(g)


# What `tolerance_on` names: the final quantity whose error the pilot estimates, from the
# final state `(g, m)` of one run (one row per body for a system of several). `None`
# where the system's group has no such part (a position on SO(3)).
MEASURES = {
    "g": lambda system, g, m: g,
    "attitude": _attitudes,
    "position": _positions,
    "momentum": lambda system, g, m: m,
    "energy": lambda system, g, m: energy(system, g, m),
}


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
    - `table`: one row per candidate (`name`, `order`, `observed_order`, `h`, `n_steps`,
      `predicted_error`, `seconds_per_body`, or `failed` with the pilot's message).
    """

    integrator: object
    h: float
    n_steps: int
    predicted_error: float
    seconds_per_body: float
    table: list[dict] = field(default_factory=list)


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
) -> Suggestion:
    """The method and step `h` that reach a final error `tolerance` over `horizon` at the
    least cost, from a pilot run of each candidate (module docstring).

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
      `‖m_h(T) − m(T)‖`), or `"energy"` (the total energy `|E_h(T) − E(T)|`,
      `lievi.diagnostics.energy`).
    - `candidates`: integrators to compare (default: `DEP()`, its compositions of order
      4, 6, 8, and `RKMK4()`, `RKMK5()`, `RKMK8()`). Each needs `order()`.
    - `h0`: the pilot's largest step (default: the step that turns `0.4` rad at the
      initial angular speed — of the fastest body, for several — at most `horizon/8`).
    - `batch`: the bodies in the pilot's timing run.

    **Returns:** a `Suggestion`. Raises `ValueError` if no candidate's pilot succeeds.
    """
    check_scalar("horizon", horizon, positive=True)
    check_scalar("tolerance", tolerance, positive=True)
    batch = check_integer("batch", batch, 1)
    horizon, tolerance = float(horizon), float(tolerance)
    system.check_element("g0", g0)
    system.check_momentum("m0", m0)
    g0, m0 = jnp.asarray(g0), jnp.asarray(m0)
    measure = _measure(system, tolerance_on, g0, m0)
    if h0 is None:
        # The fastest body's angular speed (one value per body for a system of several).
        speed = float(jnp.max(system.group.exp_norm(system.velocity(m0))))
        h0 = min(horizon / 8, 0.4 / speed) if speed > 0 else horizon / 8
    check_scalar("h0", h0, positive=True)
    candidates = default_candidates() if candidates is None else tuple(candidates)
    rows, best = [], None
    for integrator in candidates:
        row = _pilot(system, integrator, g0, m0, horizon, tolerance, float(h0), batch, measure)
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


def _pilot(system, integrator, g0, m0, horizon, tolerance, h0, batch, measure):
    order = integrator.order()
    row = {"name": f"{type(integrator).__name__} (order {order})", "order": order}
    # The pilot's steps: the largest dividing the horizon at most h₀, then its halves.
    n0 = max(1, math.ceil(horizon / h0))
    finals = []
    for level in range(3):
        solution = _final(
            system, integrator, g0[None], m0[None], horizon / (n0 * 2**level), n0 * 2**level
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
    h_fine, h_cap = horizon / (4 * n0), horizon / n0
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
