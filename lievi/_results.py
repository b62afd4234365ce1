"""Result codes: failure is data (the house style of optimistix).

Every step reports an integer code. `simulate(..., throw=True)` turns a non-success code
into an error with the message below; `throw=False` returns it in `Solution.result` so a
batch of many bodies carries on and reports which ones failed.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


class RESULTS:
    """Integer result codes of a step or a simulation, and their messages."""

    successful = 0
    newton_not_converged = 1
    step_too_large = 2  # also: past the method's documented step bound (docs/guarantees.md)
    nonfinite = 3
    invalid_input = 4
    not_run = 5  # a streamed run's body whose run has not reached its horizon (yet)
    invariant_drift = 6  # an invariant monitor's tolerance passed (`lievi.EnergyMonitor`)

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
        "the body has not been run to the end of its horizon: the streamed run "
        "(`lievi.stream_batch`) that writes it stopped, or has not reached it yet, and its "
        "saves past the last finished segment are NaN. Call `lievi.stream_batch` again with "
        "the same arguments and writer to finish it.",
        "an invariant drifted past the monitor's tolerance (`monitor=lievi.EnergyMonitor(…)` "
        "or `lievi.MomentumMonitor(…)`, checked at every save): the step is too large for "
        "what the run met (e.g. a close encounter of two bodies). Reduce the step size `h`, "
        "or loosen the monitor's `rtol`.",
    )

    @classmethod
    def message(cls, code: int) -> str:
        return cls.messages[int(code)]

    @staticmethod
    def first_failure(current, new):
        """Keep the first non-success code."""
        return jnp.where(current == RESULTS.successful, new, current)

    # The failure policy of every step loop (`simulate`'s and the kernels' in
    # `simulate_batch`), each rule once.

    @staticmethod
    def initial(valid, xp=jnp):
        """`(result, failed_step)` before the first step: `invalid_input` at step 0 where
        the input checks failed (`valid` false), else success and no failed step (−1).
        (`xp`: `numpy` for concrete `valid`.)"""
        result = xp.where(valid, RESULTS.successful, RESULTS.invalid_input)
        return result.astype(jnp.int32), xp.where(valid, -1, 0).astype(jnp.int32)

    @staticmethod
    def checked(step_result, finite, too_large):
        """A step's own code completed by the checks every method gets: a non-finite new
        state is `nonfinite` (not only the momentum: a NaN attitude too), and a step
        beyond the method's bound (`integrator.step_bound()`) is `step_too_large`,
        whatever the solve said."""
        ok = step_result == RESULTS.successful
        step_result = jnp.where(ok & ~finite, RESULTS.nonfinite, step_result)
        return jnp.where(too_large, RESULTS.step_too_large, step_result).astype(jnp.int32)

    @staticmethod
    def record(result, failed_step, k, step_result):
        """Fold step `k`'s code into the run's: the first failure is kept, with the index
        of its step. Returns `(result, failed_step, ok)`, `ok` where the run is still
        successful (after a failure the loop carries the last good state on, so later
        steps run on finite numbers and a masked failure cannot make a gradient NaN)."""
        newly_failed = (result == RESULTS.successful) & (step_result != RESULTS.successful)
        failed_step = jnp.where(newly_failed, k, failed_step)
        result = RESULTS.first_failure(result, step_result)
        return result, failed_step, result == RESULTS.successful


class StepInfo(eqx.Module):
    """Per-step report: `result` code, Newton `iterations`, final `residual` (∞-norm)."""

    result: Int[Array, ""]
    iterations: Int[Array, ""]
    residual: Float[Array, ""]
