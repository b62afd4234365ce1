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
    step_too_large = 2
    nonfinite = 3

    messages = (
        "",
        "the Newton solve of the implicit step did not reach its tolerance within "
        "`max_steps` iterations. Reduce the step size `h`, or raise `max_steps` / loosen "
        "`rtol`, `atol` of the integrator.",
        "the step's group increment left the domain of the chart (rotation angle ≥ π for "
        "the exponential chart). Reduce the step size `h`, or use chart='cayley'.",
        "a NaN or inf appeared in the state or the solve. Check the inputs (initial "
        "state, inertia, h) for NaN/inf, or reduce the step size `h`.",
    )

    @classmethod
    def message(cls, code: int) -> str:
        return cls.messages[int(code)]

    @staticmethod
    def first_failure(current, new):
        """Keep the first non-success code."""
        return jnp.where(current == RESULTS.successful, new, current)
