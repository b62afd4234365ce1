"""The report of a fit: `SystemFit` and the reason codes `FIT_REASONS`."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._systems._base import AbstractLieSystem


class FIT_REASONS:
    """Why a fit stopped: `SystemFit.reason` codes and their messages."""

    converged = 0
    max_iters = 1
    failed_samples = 2
    unidentifiable = 3
    nonfinite = 4
    stalled = 5
    misfit = 6
    boundary = 7

    messages = (
        "converged: ‖∇loss‖_∞ ≤ gtol, every sample valid, every fitted parameter identifiable.",
        "not converged: `max_iters` reached with ‖∇loss‖_∞ > gtol. Raise `max_iters`, give a "
        "better initial guess, or shorten the first horizon stage.",
        "not converged: some samples fail to simulate at the final parameters (see "
        "`failed_samples`; a step left the chart's domain). Reduce the model step `h` or "
        "improve the initial guess.",
        "not converged: the data do not determine every fitted parameter (see "
        "`identifiable`): the Gauss–Newton matrix JᵀJ of the residuals is singular at the "
        "solution. Observe a motion that excites every axis, fix the unidentifiable "
        "parameters, or give the initial momentum.",
        "not converged: the loss is not finite.",
        "not converged: the line search found no lower loss along the descent direction, "
        "nor along −∇loss, with ‖∇loss‖_∞ > gtol: the gradient is at the round-off level of "
        "the loss (raise `gtol`) or the loss is not smooth there.",
        "not converged: the data do not fit the model: the residuals at the optimum are "
        "systematic (correlated from sample to sample) rather than noise, and far above "
        "round-off. Check that the observations are this system's motion (frames, units, "
        "time step, quaternion order: `quaternion=`) and that every force acting is modelled.",
        "not converged: the fit stopped on the boundary of the parameter constraint "
        "(`realisable=True`: a triangle inequality I₁ = I₂ + I₃ holds with equality) with "
        "residuals that are systematic, not noise: a local minimum of the constrained "
        "problem, not the data's inertia. Start from another guess (the default start, "
        "`inertia=None`, estimates one from the data), or fit without `realisable`.",
    )

    @classmethod
    def message(cls, code) -> str:
        return cls.messages[int(code)]


class SystemFit(eqx.Module):
    """The result of `fit_system` / `fit_inertia` (leading batch axes when several bodies
    were fitted).

    **Attributes:**

    - `system`: the fitted system (its array leaves carry the batch axes). For a rigid
      body, `inertia` is a shortcut to `system.inertia`.
    - `params`: the fitted parameters, `params(system)` (same structure as `where` returns).
    - `m0`, `g0`: the initial momentum and orientation used (fitted if they were unknown).
    - `loss`: final loss; `loss_history`: loss at every iteration, shape `(max_iters + 1,)`,
      NaN after the last iteration taken.
    - `failed_history`: number of failed (penalised) samples at every iteration, −1 after
      the last; `failed_samples`: at the final parameters (0 for a usable fit).
    - `iterations`: optimiser iterations taken.
    - `converged`: `reason == FIT_REASONS.converged`: the relative gradient test holds
      (see `gtol` of `fit_system`), no failed sample, every fitted parameter
      identifiable, and the residuals look like noise (not a systematic misfit).
    - `reason`: a `lievi.FIT_REASONS` code; `messages()` turns it into text.
    - `identifiable`: per fitted parameter entry, whether the data determine it (same
      structure as `params`, boolean arrays); `identifiable_m0`, `identifiable_g0` for the
      fitted initial state (`None` when it was given).
    - `singular_values`: of the column-scaled residual Jacobian at the solution, largest
      first; `condition`: the ratio of the largest to the smallest (inf when singular).
    - `result`: the `RESULTS` code of the final simulation.
    """

    system: AbstractLieSystem
    params: object
    m0: Float[Array, "*batch d"]
    g0: Float[Array, "*batch n n"]
    loss: Float[Array, "*batch"]
    loss_history: Float[Array, "*batch iters"]
    failed_history: Int[Array, "*batch iters"]
    failed_samples: Int[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    reason: Int[Array, "*batch"]
    identifiable: object
    identifiable_m0: Bool[Array, "*batch d"] | None
    identifiable_g0: Bool[Array, "*batch 3"] | None
    singular_values: Float[Array, "*batch p"]
    condition: Float[Array, "*batch"]
    result: Int[Array, "*batch"]

    @property
    def inertia(self):
        """The fitted inertia, `system.inertia` (rigid bodies)."""
        return self.system.inertia

    def messages(self) -> list[str] | str:
        """`FIT_REASONS.message` of `reason` (a list over the batch)."""
        reason = np.asarray(self.reason)
        if reason.ndim == 0:
            return FIT_REASONS.message(reason)
        return [FIT_REASONS.message(r) for r in reason.ravel()]
