"""Result codes: failure is data (the house style of optimistix).

Every step reports an integer code. `simulate(..., throw=True)` turns a non-success code
into an error with the message below; `throw=False` returns it in `Solution.result` so a
batch of many bodies carries on and reports which ones failed.
"""

from __future__ import annotations

import jax.numpy as jnp


class RESULTS:
    """Integer result codes of a step or a simulation, and their messages."""

    successful = 0
    newton_not_converged = 1
    step_too_large = 2  # also: past the method's documented step bound (docs/guarantees.md)
    nonfinite = 3
    invalid_input = 4

    messages = (
        "",
        "the Newton solve of the implicit step did not reach its tolerance within "
        "`max_steps` iterations. Reduce the step size `h`, or raise `max_steps` / loosen "
        "`rtol`, `atol` of the integrator.",
        "the step is too large for the method: the angle turned in one step, h·|ξ| with "
        "ξ the velocity, exceeds the method's bound (`integrator.step_bound()`), or the "
        "increment left the domain of the chart (rotation angle ≥ π for the exponential "
        "chart), or the Moser–Veselov root is off the branch that continues h → 0. Reduce "
        "the step size `h`.",
        "a NaN or inf appeared in the state or the solve. Check the inputs (initial "
        "state, inertia, h) for NaN/inf, or reduce the step size `h`.",
        "an input is invalid (checked per body, also under jit/vmap): the system's "
        "parameters (e.g. an inertia that is not symmetric positive definite, or NaN), "
        "`g0`/`g1` not in the group (for SO(n): ‖gᵀg − I‖ + |det g − 1| > 1e-6) or not "
        "finite, `m0` or `t0` not finite, `h` not a positive normal number, or a prepared "
        "integrator used with another step size or on another trajectory. Fix the input.",
    )

    @classmethod
    def message(cls, code: int) -> str:
        return cls.messages[int(code)]

    @staticmethod
    def first_failure(current, new):
        """Keep the first non-success code."""
        return jnp.where(current == RESULTS.successful, new, current)
