"""System identification: fit chosen parameters of a system to observed orientations /
angular velocities.

The model is the discrete trajectory itself: `simulate(system, integrator, g₀, m₀)` sampled
every `sample_every` steps, differentiated end to end (each Newton solve by the implicit
function theorem, `_newton.py`). The loss is the weighted mean over samples of the squared
residuals

    r_k = ( √w_R (g_k − R_k),  √w_Ω (Ω_k − Ω̂_k) ),     Ω_k = velocity(m_k),

minimised by L-BFGS with a backtracking line search (`_fit_optimizer.py`), or by any optax
transformation such as Adam, over any subset of the
system's parameters (chosen by a `where` function, as in `eqx.tree_at`) together with the
initial state when it is unknown. The fitted leaves are optimised in unconstrained
coordinates: the inertia of a rigid body through a parametrisation that keeps it symmetric
positive definite, and on request physically realisable (the triangle inequalities
`I₁ ≤ I₂ + I₃`, …): the inertia of a mass distribution with second-moment matrix
`Σ = ∫ x xᵀ dm ≻ 0` is `I = tr(Σ)·1 − Σ`; with `Σ = diag(Λ)` this is the paper's
`I₁ = Λ₂ + Λ₃, I₂ = Λ₁ + Λ₃, I₃ = Λ₁ + Λ₂` (§5). Every other fitted leaf is fitted as is.

**Gauge.** Scaling `(I, Π₀, V) ↦ (cI, cΠ₀, cV)` leaves every discrete increment unchanged
(the DEP equation `Π_k = dφ⁻¹(ξ_k)ᵀ I ξ_k/h − (h/2)·dV` is homogeneous of degree one in
`(I, Π, V)`), hence every orientation `g_k` and every angular velocity `I⁻¹Π_k`. When Π₀ is
unknown and the inertia is fitted (with the potential's scale, e.g. `m ρ` of gravity,
fitted too or no potential at all) only the ratios are observable, and the fit fixes the
gauge explicitly: the trace of the inertia is held at `trace`. With Π₀ known, or a fixed
potential, the scale is fitted too.

**Identifiability.** At the solution the Jacobian `J` of the residuals with respect to the
fitted physical parameters (restricted to the gauge) is computed by forward-mode autodiff.
Its columns are scaled to unit norm (so units do not matter); a singular value of the
scaled `J` below `identifiability_rtol` times the largest is a direction in which the data
do not determine the parameters (a flat valley of the loss: a body spinning about a
principal axis does not reveal its other two moments; a body at rest reveals none). A
parameter is reported unidentifiable when such a direction moves it, and the fit then says
`converged=False` with the reason, whatever the optimiser's stopping test said.

**Failures.** A trial parameter can make a step fail (e.g. a rotation ≥ π in one step). Such
samples are not dropped (that would reward failing) but charged a fixed penalty — the
largest possible orientation error, `‖g − R‖_F² ≤ 8`, and `4 max_k ‖Ω_k‖²` for velocities —
whose gradient is zero; the count of failed samples is reported at every iteration.

**Batches.** Leading batch axes on the observations fit many bodies in one call. Every
loss evaluation is one `simulate_batch` call for all bodies (the structure-of-arrays fast
path and its reverse mode, where the system and integrator have one), and the optimiser is
a per-body state machine that needs exactly one evaluation per tick (`_fit_optimizer.py`):
a body in its line search and a body starting a new iteration share each evaluation, and
none waits for the longest line search of the batch. Large batches run in rounds of
`check_every` ticks: after each round the bodies that have finished leave the batch and the
others continue in a smaller one.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from ._checks import check_finite, is_concrete, membership_tolerance
from ._fit_optimizer import LBFGS, OptaxMachine
from ._groups._so3 import SO3
from ._integrators._base import AbstractIntegrator
from ._integrators._dep import DEP
from ._simulate import simulate
from ._simulate_batch import simulate_batch
from ._systems._base import AbstractLieSystem
from ._systems._rigid_body import RigidBody

_ORIENTATION_PENALTY = 8.0  # max ‖g − R‖_F² over rotations g, R


class FIT_REASONS:
    """Why a fit stopped: `SystemFit.reason` codes and their messages."""

    converged = 0
    max_iters = 1
    failed_samples = 2
    unidentifiable = 3
    nonfinite = 4
    stalled = 5

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
    - `converged`: `reason == FIT_REASONS.converged`: ‖∇loss‖_∞ ≤ `gtol`, no failed sample,
      and every fitted parameter identifiable.
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


InertiaFit = SystemFit  # the result of `fit_inertia` (earlier name, kept)


# ---- parametrisations: unconstrained θ ↔ inertia --------------------------------------


def _to_inertia(theta, tensor: bool, realisable: bool):
    if not tensor:
        positive = jnp.exp(theta)
        if realisable:  # positive = Λ (Σ = diag Λ)
            return jnp.sum(positive) - positive
        return positive
    # Lower-triangular factor with positive diagonal: SPD for every θ.
    L = jnp.zeros((3, 3), theta.dtype).at[jnp.tril_indices(3)].set(theta)
    L = L.at[jnp.diag_indices(3)].set(jnp.exp(jnp.diagonal(L)))
    spd = L @ L.T
    if realisable:  # spd = Σ
        return jnp.trace(spd) * jnp.eye(3, dtype=theta.dtype) - spd
    return spd


def _from_inertia(inertia, tensor: bool, realisable: bool):
    """θ with `_to_inertia(θ) = inertia` (concrete input; raises if not representable)."""
    inertia = np.asarray(inertia, dtype=float)
    if not tensor:
        target = (np.sum(inertia) / 2 - inertia) if realisable else inertia
        if np.any(target <= 0):
            raise ValueError(
                "`inertia` (initial guess) must be positive"
                + (
                    " and satisfy the strict triangle inequalities I₁ < I₂ + I₃, …"
                    if realisable
                    else ""
                )
                + f"; got {inertia}."
            )
        return np.log(target)
    target = (np.trace(inertia) / 2 * np.eye(3) - inertia) if realisable else inertia
    try:
        L = np.linalg.cholesky(target)
    except np.linalg.LinAlgError:
        raise ValueError(
            "`inertia` (initial guess) must be symmetric positive definite"
            + (" and physically realisable (tr(I)/2 − I ≻ 0)" if realisable else "")
            + "."
        ) from None
    L[np.diag_indices(3)] = np.log(np.diagonal(L))
    return L[np.tril_indices(3)]


def _trace(inertia):
    return jnp.sum(inertia) if inertia.ndim == 1 else jnp.trace(inertia)


class _Leaf(eqx.Module):
    """How one fitted leaf is parametrised: `kind` is "free", "moments" or "tensor"."""

    index: int = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    shape: tuple = eqx.field(static=True)


class _Marker:
    def __init__(self, index):
        self.index = index


def _selected_indices(system, where, what="params") -> tuple[int, ...]:
    """Flat leaf indices of `system` that `where(system)` selects (no repeats)."""
    leaves, treedef = jax.tree.flatten(system)
    marked = jax.tree.unflatten(treedef, [_Marker(i) for i in range(len(leaves))])
    try:
        chosen = where(marked)
    except Exception as error:
        raise ValueError(f"`{what}` could not be applied to the system: {error}") from error
    chosen = jax.tree.leaves(chosen, is_leaf=lambda x: isinstance(x, _Marker))
    if not chosen or not all(isinstance(x, _Marker) for x in chosen):
        raise ValueError(
            f"`{what}` must return leaves of the system (arrays, e.g. `lambda s: s.inertia` or "
            "`lambda s: (s.inertia, s.potential.center_of_mass)`), and at least one."
        )
    indices = tuple(x.index for x in chosen)
    if len(set(indices)) != len(indices):
        raise ValueError(f"`{what}` selects a leaf twice.")
    return indices


# ---- the fit --------------------------------------------------------------------------


def fit_system(
    system: AbstractLieSystem,
    orientations: Float[Array, "*batch S n n"] | None = None,
    angular_velocities: Float[Array, "*batch S d"] | None = None,
    *,
    h,
    sample_every: int,
    params: Callable = lambda s: s.inertia,
    m0=None,
    g0=None,
    system_axis: int | None = None,
    realisable: bool = False,
    trace=None,
    integrator: AbstractIntegrator = DEP(),
    optimizer: str | optax.GradientTransformation = "lbfgs",
    learning_rate: float = 1e-2,
    max_iters: int = 500,
    gtol: float | None = None,
    horizons: tuple[int, ...] | None = None,
    orientation_weight=1.0,
    velocity_weight=1.0,
    identifiability_rtol: float | None = None,
    check_every: int | None = None,
) -> SystemFit:
    """Fit chosen parameters of `system` (and Π₀, g₀ when unknown) to observations.

    Sample `k` (`k = 0, …, S − 1`) is taken at step `k·sample_every`, time `k·sample_every·h`.
    Leading batch axes on the observations fit many bodies at once; the other arrays are
    shared or carry the same batch axes.

    **Arguments:**

    - `system`: the model with the initial guess of the fitted parameters and the known
      values of the others, e.g. `lievi.heavy_top(I_guess, mass, ρ_guess)`.
    - `orientations`: observed attitudes `R_k`, shape `(*batch, S, n, n)` (noisy rotation
      vectors `r_k` become `lievi.SO3.exp(r_k)`); rotations to 1e-6.
    - `angular_velocities`: observed velocities `Ω_k = velocity(m_k)` (body angular
      velocities `I⁻¹Π_k` for a rigid body), `(*batch, S, d)`. Give at least one of the two.
    - `h`, `sample_every`: step size of the model and steps between samples.
    - `params`: a function selecting the fitted leaves, as `where` of `eqx.tree_at`:
      `lambda s: s.inertia` (default), `lambda s: (s.inertia, s.potential.center_of_mass)`,
      … A rigid body's `inertia` stays positive definite (principal moments `(3,)` or a
      tensor `(3, 3)`, by its shape); other leaves are unconstrained.
    - `m0`: the known initial momentum, or `None` to fit it (initial guess from the first
      two samples). Then, if the inertia is fitted, the gauge is fixed by its trace.
    - `g0`: the known initial orientation, or `None` to fit it (initial guess `R_0`).
    - `system_axis`: `None` (one initial guess for every body) or `0` (every array leaf of
      `system` carries the batch axes first, e.g. `jax.vmap(lievi.RigidBody)(guesses)`).
    - `realisable`: constrain the inertia to physically realisable ones (triangle inequalities).
    - `trace`: the gauge (> 0), used only when it applies; default the trace of the guess.
    - `integrator`: the model integrator (default `DEP()`, exponential chart).
    - `optimizer`: `"lbfgs"` (L-BFGS, memory 10, backtracking line search with the Armijo
      or the approximate Wolfe conditions), `"adam"` (`optax.adam` at `learning_rate`), or
      any `optax.GradientTransformation` (used as `update(g, s, p)`, one loss evaluation per
      iteration).
    - `max_iters`, `gtol`: stop when `‖∇loss‖_∞ ≤ gtol` (gradient in the unconstrained
      parameters; default 1e-11 in float64, 1e-4 in float32 — where round-off in a
      400-step simulation already puts the gradient at the optimum near 2e-5) or after
      `max_iters`.
    - `horizons`: continuation in the observed horizon. Over many periods the loss is far
      from convex in the parameters (a wrong inertia puts the trajectory out of phase), so
      the fit first uses only the first `horizons[0]` samples, then the first
      `horizons[1]`, …, each stage started from the previous one's solution and run until
      `‖∇loss‖_∞ ≤ √gtol` (the last stage: `gtol`). Default: 4, 8, 16, … up to `S`. One
      compilation for all stages (the stage only changes a mask).
    - `orientation_weight`, `velocity_weight`: `w_R`, `w_Ω` of the loss: scalars, or one
      weight per sample, shape `(S,)` or `(*batch, S)`. With Gaussian noise of known size
      `σ_k` on sample `k`, `w_k = 1/σ_k²` makes the fit the maximum-likelihood estimate.
    - `identifiability_rtol`: a singular value of the column-scaled residual Jacobian below
      this times the largest marks an unidentifiable direction (default `ε^(1/3)` of the
      dtype: 6e-6 in float64, 5e-3 in float32).
    - `check_every`: batched fits run in rounds of this many loss evaluations (about one
      per iteration), after each of
      which finished bodies leave the batch (default 20 for 64 bodies or more; otherwise
      one round). Results do not depend on it.

    **Returns:** a `SystemFit`.
    """
    if not isinstance(system, AbstractLieSystem):
        raise ValueError(
            f"`system` must be a lievi system (e.g. lievi.RigidBody), got {type(system).__name__}."
        )
    if orientations is None and angular_velocities is None:
        raise ValueError("Give `orientations` and/or `angular_velocities` to fit to.")
    if g0 is None and orientations is None:
        raise ValueError("`g0` is needed when no `orientations` are observed.")
    for name, value, low in (("sample_every", sample_every, 1), ("max_iters", max_iters, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"`{name}` must be an integer ≥ {low}, got {value!r}.")
    if check_every is not None and (
        isinstance(check_every, bool)
        or not isinstance(check_every, (int, np.integer))
        or check_every < 1
    ):
        raise ValueError(f"`check_every` must be None or an integer ≥ 1, got {check_every!r}.")
    if isinstance(optimizer, str) and optimizer not in ("lbfgs", "adam"):
        raise ValueError(
            f"`optimizer` must be 'lbfgs', 'adam' or an optax transformation, got {optimizer!r}."
        )
    for name, value in (
        ("learning_rate", learning_rate),
        ("gtol", gtol),
        ("identifiability_rtol", identifiability_rtol),
    ):
        if value is None:
            continue
        if jnp.ndim(value) != 0 or not is_concrete(value) or not np.isfinite(float(value)):
            raise ValueError(f"`{name}` must be a finite Python number, got {value!r}.")
        if float(value) < 0 or (name != "gtol" and float(value) == 0):
            raise ValueError(
                f"`{name}` must be {'≥' if name == 'gtol' else '>'} 0, got {float(value)}."
            )
    if jnp.ndim(h) != 0:
        raise ValueError(f"`h` must be a scalar step size, got shape {jnp.shape(h)}.")
    if is_concrete(h):
        check_finite("h", h)
        if not float(h) > 0:
            raise ValueError(f"`h` must be > 0, got {float(h)}; pass a positive step size.")
    if system_axis not in (None, 0):
        raise ValueError(f"`system_axis` must be None or 0, got {system_axis!r}.")

    group = system.group
    n, d = group.matrix_dim, group.algebra_dim
    obs = orientations if orientations is not None else angular_velocities
    obs_core = 3 if orientations is not None else 2
    batch_shape = tuple(jnp.shape(obs)[: jnp.ndim(obs) - obs_core])
    n_samples = jnp.shape(obs)[len(batch_shape)]
    if n_samples < 2:
        raise ValueError(f"need at least 2 samples per body, got {n_samples}.")
    if orientations is not None:
        _check_trailing("orientations", orientations, batch_shape, (n_samples, n, n))
        _check_rotations("orientations", orientations, group)
    if angular_velocities is not None:
        _check_trailing("angular_velocities", angular_velocities, batch_shape, (n_samples, d))
    if g0 is None and n != 3:
        raise ValueError("Fitting `g0` is implemented on SO(3); give `g0` for other groups.")
    m0 = None if m0 is None else _batched("m0", m0, batch_shape, (d,))
    g0 = None if g0 is None else _batched("g0", g0, batch_shape, (n, n))
    if m0 is not None:
        check_finite("m0", m0)
    if g0 is not None:
        check_finite("g0", g0)
        _check_rotations("g0", g0, group)
    trace = None if trace is None else _batched("trace", trace, batch_shape, ())
    if trace is not None:
        check_finite("trace", trace)
        if is_concrete(trace) and np.any(np.asarray(trace) <= 0):
            raise ValueError(f"`trace` (the gauge) must be > 0, got {np.asarray(trace)}.")
    weights = []
    for name, w in (
        ("orientation_weight", orientation_weight),
        ("velocity_weight", velocity_weight),
    ):
        w = jnp.broadcast_to(w, (n_samples,)) if jnp.ndim(w) == 0 else w
        w = _batched(name, w, batch_shape, (n_samples,))
        check_finite(name, w)
        if is_concrete(w) and np.any(np.asarray(w) < 0):
            raise ValueError(f"`{name}` must be ≥ 0.")
        weights.append(w)

    # ---- the fitted leaves and their parametrisations
    indices = _selected_indices(system, params)
    leaves, treedef = jax.tree.flatten(system)
    inertia_index = None
    if isinstance(system, RigidBody):
        inertia_index = _selected_indices(system, lambda s: s.inertia, "inertia")[0]
    fitted = []
    for i in indices:
        value = leaves[i]
        if not is_concrete(value):
            raise ValueError(
                "The fitted parameters' initial guesses must be concrete arrays, not traced."
            )
        if not eqx.is_array_like(value) or not np.isrealobj(np.asarray(value)):
            raise ValueError(
                f"`params` selected a leaf that is not a real array: {type(value).__name__}."
            )
        value = np.asarray(value, float)
        core = value.shape[len(batch_shape) :] if system_axis == 0 else value.shape
        if system_axis == 0 and value.shape[: len(batch_shape)] != batch_shape:
            raise ValueError(
                f"with `system_axis=0` every fitted leaf must carry the batch axes {batch_shape} first, "
                f"got shape {value.shape}."
            )
        check_finite("params", value)
        if i == inertia_index:
            kind = "tensor" if core == (3, 3) else "moments"
            if kind == "moments" and core != (3,):
                raise ValueError(f"`inertia` must have shape (3,) or (3, 3), got {core}.")
        else:
            kind = "free"
        fitted.append(_Leaf(i, kind, tuple(core)))
    fitted = tuple(fitted)
    if realisable and not any(f.kind != "free" for f in fitted):
        raise ValueError(
            "`realisable=True` constrains the inertia, which is not among the fitted `params`."
        )

    dtype = jnp.result_type(
        *[x for x in (orientations, angular_velocities, m0, g0, h) if x is not None],
        *[x for x in leaves if eqx.is_inexact_array(x)],
        float,
    )
    # The system's arrays (and the fitted leaves, whatever their type) become the batched
    # dynamic part; the rest (functions, static fields) is closed over.
    leaves = list(leaves)
    for f in fitted:
        leaves[f.index] = jnp.asarray(leaves[f.index], dtype)
    system = jax.tree.unflatten(treedef, leaves)
    dynamic, static = eqx.partition(system, eqx.is_array)
    if system_axis is None:
        dynamic = jax.tree.map(lambda x: jnp.broadcast_to(x, batch_shape + jnp.shape(x)), dynamic)

    theta0 = []
    for f in fitted:
        value = np.asarray(leaves[f.index], float)
        value = np.broadcast_to(value, batch_shape + f.shape) if system_axis is None else value
        if f.kind == "free":
            theta0.append(jnp.asarray(value, dtype))
        else:
            flat = value.reshape((-1,) + f.shape)
            theta = np.stack([_from_inertia(x, f.kind == "tensor", realisable) for x in flat])
            theta0.append(jnp.asarray(theta.reshape(batch_shape + theta.shape[1:]), dtype))
    inertia_leaf = next((f for f in fitted if f.kind != "free"), None)
    gauge = (
        m0 is None
        and inertia_leaf is not None
        and (system.potential is None or any(f.kind == "free" for f in fitted))
    )
    if gauge and trace is None:
        guess = np.asarray(leaves[inertia_leaf.index], float)
        guess = (
            np.broadcast_to(guess, batch_shape + inertia_leaf.shape)
            if system_axis is None
            else guess
        )
        trace = (
            np.trace(guess, axis1=-2, axis2=-1) if inertia_leaf.kind == "tensor" else guess.sum(-1)
        )
    trace = jnp.asarray(trace, dtype) if gauge else None

    if gtol is None:
        # float32: the gradient's round-off floor (≈ 2e-5 at the optimum of a 400-step
        # HLW fit, measured) must lie below the tolerance.
        gtol = 1e-11 if jnp.finfo(dtype).bits >= 64 else 1e-4
    if identifiability_rtol is None:
        identifiability_rtol = float(jnp.finfo(dtype).eps) ** (1 / 3)
    if horizons is None:
        horizons = tuple(
            min(4 * 2**i, n_samples)
            for i in range(int(np.ceil(np.log2(max(n_samples / 4, 1)))) + 1)
        )
    horizons = tuple(int(x) for x in horizons)
    if (
        not horizons
        or horizons[-1] != n_samples
        or any(b <= a for a, b in zip(horizons, horizons[1:]))
        or horizons[0] < 2
    ):
        raise ValueError(
            f"`horizons` must increase from ≥ 2 to the number of samples ({n_samples}), got {horizons}."
        )

    cast = lambda x: None if x is None else jnp.asarray(x, dtype)
    n_bodies = int(np.prod(batch_shape)) if batch_shape else 1
    flat = lambda x: (
        None if x is None else jnp.reshape(x, (n_bodies,) + jnp.shape(x)[len(batch_shape) :])
    )
    data = dict(
        orientations=cast(orientations),
        angular_velocities=cast(angular_velocities),
        m0=cast(m0),
        g0=cast(g0),
        trace=trace,
        weights=tuple(map(cast, weights)),
    )
    data = jax.tree.map(flat, data)
    dynamic = jax.tree.map(flat, dynamic)
    theta0 = [flat(t) for t in theta0]

    config = _Config(
        static=static,
        fitted=fitted,
        integrator=integrator,
        sample_every=int(sample_every),
        n_samples=int(n_samples),
        realisable=bool(realisable),
        optimizer=optimizer,
        learning_rate=float(learning_rate),
        max_iters=int(max_iters),
        gtol=float(gtol),
        horizons=horizons,
        rtol=float(identifiability_rtol),
    )
    h = jnp.asarray(h, dtype)
    carry = _start(config, theta0, dynamic, data, h)
    if check_every is None and n_bodies >= 64:
        check_every = 20
    carry = _iterate(config, check_every, carry, dynamic, data, h)
    out = _finish(config, carry, dynamic, data, h)
    out = jax.tree.map(lambda x: jnp.reshape(x, batch_shape + jnp.shape(x)[1:]), out)
    fitted_system = _replace_leaves(config, eqx.combine(out.system, static), out.params)
    flag_tree = _replace_leaves(config, eqx.combine(out.system, static), out.identifiable)
    return eqx.tree_at(
        lambda f: (f.system, f.params, f.identifiable),
        out,
        (fitted_system, params(fitted_system), params(flag_tree)),
        is_leaf=lambda x: x is None,
    )


def _replace_leaves(config, system, values):
    leaves, treedef = jax.tree.flatten(system)
    for f, v in zip(config.fitted, values):
        leaves[f.index] = v
    return jax.tree.unflatten(treedef, leaves)


def fit_inertia(
    orientations: Float[Array, "*batch S 3 3"] | None = None,
    angular_velocities: Float[Array, "*batch S 3"] | None = None,
    *,
    h,
    sample_every: int,
    inertia,
    m0=None,
    g0=None,
    tensor: bool = False,
    realisable: bool = False,
    trace=None,
    integrator: AbstractIntegrator = DEP(),
    optimizer: str | optax.GradientTransformation = "lbfgs",
    learning_rate: float = 1e-2,
    max_iters: int = 500,
    gtol: float | None = None,
    horizons: tuple[int, ...] | None = None,
    orientation_weight=1.0,
    velocity_weight=1.0,
    identifiability_rtol: float | None = None,
    check_every: int | None = None,
) -> SystemFit:
    """Fit the inertia (and Π₀, g₀ when unknown) of free rigid bodies to observations.

    `fit_system(lievi.RigidBody(inertia), …, params=lambda s: s.inertia)`; see `fit_system`
    for every argument and the report.

    **Arguments** (beyond `fit_system`'s):

    - `inertia`: initial guess, principal moments `(3,)` (or a tensor `(3, 3)` with
      `tensor=True`), shared or one per body `(*batch, 3)`.
    - `tensor`: fit a full SPD tensor (6 parameters) instead of principal moments (3).

    **Returns:** a `SystemFit` (`fit.inertia` is the fitted inertia).
    """
    obs = orientations if orientations is not None else angular_velocities
    if obs is None:
        raise ValueError("Give `orientations` and/or `angular_velocities` to fit to.")
    core = (3, 3) if tensor else (3,)
    batch_shape = tuple(jnp.shape(obs)[: jnp.ndim(obs) - (3 if orientations is not None else 2)])
    inertia = _batched("inertia", inertia, batch_shape, core)
    if not is_concrete(inertia):
        raise ValueError("`inertia` (the initial guess) must be a concrete array, not traced.")
    check_finite("inertia", inertia)
    if jnp.shape(inertia) == core:
        system, axis = (
            RigidBody(jnp.asarray(np.asarray(inertia, float)) if tensor else inertia),
            None,
        )
        _from_inertia(inertia, tensor, realisable)  # the guess's own error message first
    else:
        flat = np.asarray(inertia, float).reshape((-1,) + core)
        for x in flat:
            _from_inertia(x, tensor, realisable)
        make = RigidBody
        for _ in batch_shape:
            make = jax.vmap(make)
        system, axis = make(jnp.asarray(inertia)), 0
    return fit_system(
        system,
        orientations,
        angular_velocities,
        h=h,
        sample_every=sample_every,
        params=lambda s: s.inertia,
        m0=m0,
        g0=g0,
        system_axis=axis,
        realisable=realisable,
        trace=trace,
        integrator=integrator,
        optimizer=optimizer,
        learning_rate=learning_rate,
        max_iters=max_iters,
        gtol=gtol,
        horizons=horizons,
        orientation_weight=orientation_weight,
        velocity_weight=velocity_weight,
        identifiability_rtol=identifiability_rtol,
        check_every=check_every,
    )


# ---- argument helpers -----------------------------------------------------------------


def _check_trailing(name, x, batch_shape, core):
    if tuple(jnp.shape(x)) != tuple(batch_shape) + tuple(core):
        raise ValueError(
            f"`{name}` must have shape {tuple(batch_shape) + tuple(core)} (batch axes, then "
            f"{core}), got {tuple(jnp.shape(x))}."
        )
    check_finite(name, x)


def _check_rotations(name, x, group):
    """Every `(n, n)` matrix of `x` in the group (orthogonal, det +1) to 1e-6 (float64)."""
    if not is_concrete(x):
        return
    x = np.asarray(x)
    tol = membership_tolerance(x.dtype)
    with jax.ensure_compile_time_eval():
        defect = np.asarray(group.membership_defect(jnp.asarray(x, float)))
    if np.any(defect > tol):
        worst = np.unravel_index(np.argmax(defect), defect.shape)
        raise ValueError(
            f"`{name}` must hold rotation matrices (orthogonal, det +1); entry {tuple(int(i) for i in worst)} "
            f"has membership defect {float(defect.max()):.3g} > {tol:.1g}. Orthonormalise with a "
            "QR or polar decomposition, or build them with lievi.SO3.exp(rotation_vectors)."
        )


def _batched(name, x, batch_shape, core):
    """Broadcast a shared or per-body argument to `batch_shape + core`."""
    shape = tuple(jnp.shape(x))
    if shape == tuple(core):
        return jnp.broadcast_to(x, tuple(batch_shape) + tuple(core)) if batch_shape else x
    if shape == tuple(batch_shape) + tuple(core):
        return x
    raise ValueError(
        f"`{name}` must have shape {tuple(core)} (shared) or {tuple(batch_shape) + tuple(core)} "
        f"(one per body), got {shape}."
    )


# ---- one body: model, loss, optimiser state -------------------------------------------


class _Config(eqx.Module):
    """Everything static about a fit (hashable: one compilation per configuration)."""

    static: AbstractLieSystem = eqx.field(static=True)
    fitted: tuple = eqx.field(static=True)
    integrator: AbstractIntegrator = eqx.field(static=True)
    sample_every: int = eqx.field(static=True)
    n_samples: int = eqx.field(static=True)
    realisable: bool = eqx.field(static=True)
    optimizer: object = eqx.field(static=True)
    learning_rate: float = eqx.field(static=True)
    max_iters: int = eqx.field(static=True)
    gtol: float = eqx.field(static=True)
    horizons: tuple = eqx.field(static=True)
    rtol: float = eqx.field(static=True)

    # -- the model
    def leaf_values(self, theta, data):
        """Physical values of the fitted leaves from unconstrained θ (gauge applied)."""
        values = []
        for f, t in zip(self.fitted, theta):
            if f.kind == "free":
                values.append(t)
                continue
            inertia = _to_inertia(t, f.kind == "tensor", self.realisable)
            if data["trace"] is not None:  # the gauge (see the module docstring)
                inertia = inertia * (data["trace"] / _trace(inertia))
            values.append(inertia)
        return values

    def system_of(self, values, dynamic):
        system = eqx.combine(dynamic, self.static)
        leaves, treedef = jax.tree.flatten(system)
        for f, v in zip(self.fitted, values):
            leaves[f.index] = v
        return jax.tree.unflatten(treedef, leaves)

    @property
    def n_steps(self):
        return (self.n_samples - 1) * self.sample_every

    def residuals(self, system, m0, g0, data, h, horizon):
        """One body: weighted residual vector, failed-sample penalty, count of failed
        samples, result."""
        sol = simulate(
            system,
            self.integrator,
            g0,
            m0,
            h=h,
            n_steps=self.n_steps,
            save_every=self.sample_every,
            throw=False,
        )
        return (*self.residual_terms(system, sol.g, sol.m, data, horizon), sol.result)

    def residual_terms(self, system, g, m, data, horizon):
        """Weighted residual vector, failed-sample penalty and count of failed samples of
        one body's simulated samples `g`, `m`."""
        dtype = m.dtype
        valid = jnp.all(jnp.isfinite(m), axis=-1) & jnp.all(jnp.isfinite(g), axis=(-2, -1))
        counted = (jnp.arange(self.n_samples) < horizon).astype(dtype)
        parts, penalty = [], jnp.zeros((), dtype)
        w_orientation, w_velocity = data["weights"]
        if data["orientations"] is not None:
            R = data["orientations"]
            # double where: a failed (NaN) sample never enters arithmetic, so no NaN gradient
            g = jnp.where(valid[:, None, None], g, R)
            weight = w_orientation * counted / jnp.sum(counted)  # weighted mean over this stage
            parts.append((jnp.sqrt(weight)[:, None, None] * (g - R)).ravel())
            penalty = penalty + jnp.sum(jnp.where(valid, 0.0, weight * _ORIENTATION_PENALTY))
        if data["angular_velocities"] is not None:
            W = data["angular_velocities"]
            m = jnp.where(valid[:, None], m, 0.0)
            omega = jnp.where(valid[:, None], jax.vmap(system.velocity)(m), W)
            weight = w_velocity * counted / jnp.sum(counted)
            parts.append((jnp.sqrt(weight)[:, None] * (omega - W)).ravel())
            worst = 4 * jnp.max(jnp.sum(W**2, axis=-1))
            penalty = penalty + jnp.sum(jnp.where(valid, 0.0, weight * worst))
        failed = jnp.sum(~valid & (counted > 0)).astype(jnp.int32)
        return jnp.concatenate(parts), penalty, failed

    def unpack(self, params, dynamic, data):
        values = self.leaf_values(params["theta"], data)
        m0 = data["m0"] if data["m0"] is not None else params["m0"]
        g0 = (
            data["g0"]
            if data["g0"] is not None
            else data["orientations"][0] @ SO3.exp(params["g0_chart"])
        )
        return values, m0, g0

    def batch_loss(self, params, dynamic, data, h, horizon):
        """Every body's loss at once, through `simulate_batch` (its structure-of-arrays fast
        path and that path's reverse mode where the system and integrator have one).

        **Returns:** `(Σ losses, (losses, failed, result))`: the bodies are independent, so
        the gradient of the sum is every body's own gradient."""
        dtype = h.dtype
        params = jax.tree.map(lambda x: x.astype(dtype), params)
        values, m0, g0 = jax.vmap(self.unpack)(params, dynamic, data)
        systems = jax.vmap(self.system_of)(values, dynamic)
        sol = simulate_batch(
            systems,
            self.integrator,
            g0,
            m0,
            h=h,
            n_steps=self.n_steps,
            save_every=self.sample_every,
            save=("g", "m"),
            system_axis=0,
            throw=False,
        )
        r, penalty, failed = jax.vmap(self.residual_terms)(systems, sol.g, sol.m, data, horizon)
        losses = jnp.sum(r**2, axis=-1) + penalty
        return jnp.sum(losses), (losses, failed, sol.result)

    # -- the optimiser
    def machine(self):
        if isinstance(self.optimizer, str) and self.optimizer == "lbfgs":
            return LBFGS()
        if isinstance(self.optimizer, str):
            return OptaxMachine(optax.adam(self.learning_rate))
        return OptaxMachine(self.optimizer)

    @property
    def stage_gtol(self):
        return max(self.gtol, np.sqrt(self.gtol)) if len(self.horizons) > 1 else self.gtol


def _stage_done(config, value, failed, gnorm, stage):
    last = len(config.horizons) - 1
    tol = jnp.where(stage == last, config.gtol, config.stage_gtol)
    return (gnorm <= tol) & (failed == 0) & jnp.isfinite(value)


class _Carry(eqx.Module):
    params: dict  # the accepted point
    opt: object  # the optimiser's state (`_fit_optimizer`)
    failed: Array  # failed samples at the accepted point
    stage: Array
    it: Array
    history: Array
    failed_history: Array
    done: Array  # the current stage's stopping test holds at the accepted point
    finished: Array


def _initial_params(config, theta0, dynamic, data, h):
    dtype = h.dtype
    params = {"theta": list(theta0)}
    if data["m0"] is None:  # unknown Π₀: from the first two samples, Π₀ ≈ legendre(Ω₀)
        values = config.leaf_values(params["theta"], data)
        system = config.system_of(values, dynamic)
        if data["orientations"] is not None:
            R = data["orientations"]
            omega0 = SO3.log(R[0].T @ R[1]) / (config.sample_every * h)
        else:
            omega0 = data["angular_velocities"][0]
        params["m0"] = system.legendre(omega0).astype(dtype)
    if data["g0"] is None:
        params["g0_chart"] = jnp.zeros(3, dtype)
    return params


def _flat(params):
    return ravel_pytree(params)[0]


def _digest(config, machine, unravel, c: _Carry, value, grad, failed) -> _Carry:
    """One body takes in the loss and gradient at its trial point (`_fit_optimizer`)."""
    last = len(config.horizons) - 1
    opt, accepted = machine.tell(c.opt, value, grad)
    it = c.it + (accepted & ~c.opt.fresh).astype(c.it.dtype)
    # The loss at the accepted point (a new stage re-evaluates it over its longer horizon).
    history = jnp.where(accepted, c.history.at[it].set(value), c.history)
    failed_history = jnp.where(accepted, c.failed_history.at[it].set(failed), c.failed_history)
    failed = jnp.where(accepted, failed, c.failed)
    gnorm = jnp.max(jnp.abs(grad))
    done = jnp.where(accepted, _stage_done(config, value, failed, gnorm, c.stage), c.done)
    # A finished stage hands its solution to the next, longer horizon (the loss has
    # changed: the point is evaluated again and the curvature memory dropped).
    next_stage = done & (c.stage < last)
    finished = (done & (c.stage == last)) | (it >= config.max_iters) | opt.stalled
    point = unravel(opt.x)  # (an optax machine's `advance` moves `x` on)
    advanced = machine.advance(opt)
    restarted = machine.restart(opt)
    opt = jax.tree.map(
        lambda r, a, o: jnp.where(next_stage, r, jnp.where(accepted & ~finished, a, o)),
        restarted,
        advanced,
        opt,
    )
    new = _Carry(
        params=jax.tree.map(lambda old, x: jnp.where(accepted, x, old), c.params, point),
        opt=opt,
        failed=failed,
        stage=jnp.where(next_stage, c.stage + 1, c.stage),
        it=it,
        history=history,
        failed_history=failed_history,
        done=done & ~next_stage,
        finished=finished,
    )
    return jax.tree.map(lambda n, o: jnp.where(c.finished, o, n), new, c)


def _identifiability(config, params, dynamic, data, h):
    """Singular values of the column-scaled residual Jacobian (in the physical fitted
    parameters, restricted to the gauge) and, per parameter entry, whether it lies off
    every (near-)null direction."""
    dtype = h.dtype
    values, m0, g0 = config.unpack(params, dynamic, data)
    physical = {"values": values}
    if data["m0"] is None:
        physical["m0"] = m0
    if data["g0"] is None:
        physical["g0_chart"] = params["g0_chart"].astype(dtype)
    flat, unravel = ravel_pytree(physical)
    horizon = config.horizons[-1]

    def residual(p):
        phys = unravel(p)
        # a tensor is perturbed symmetrically (its lower entries mirror the upper ones)
        vals = [
            jnp.triu(v) + jnp.triu(v, 1).T if f.kind == "tensor" else v
            for f, v in zip(config.fitted, phys["values"])
        ]
        m = phys.get("m0", m0)
        g = g0 if "g0_chart" not in phys else data["orientations"][0] @ SO3.exp(phys["g0_chart"])
        return config.residuals(config.system_of(vals, dynamic), m, g, data, h, horizon)[0]

    def marks(kind_value):
        """A vector over the physical coordinates from one array per fitted leaf."""
        tree = {"values": [kind_value(f) for f in config.fitted]}
        for key in ("m0", "g0_chart"):
            if key in physical:
                tree[key] = np.zeros(jnp.shape(physical[key]))
        return np.concatenate(
            [np.ravel(np.asarray(x, float)) for x in jax.tree.leaves(tree)]
        )  # ravel_pytree's order

    # Admissible perturbations: upper-triangular entries of tensors; with the gauge, the
    # inertia's trace held.
    lower = marks(
        lambda f: np.tril(np.ones((3, 3)), -1) if f.kind == "tensor" else np.zeros(f.shape)
    )
    keep = np.flatnonzero(lower == 0)
    basis = np.eye(flat.shape[0])[:, keep]
    if data["trace"] is not None:
        c = marks(
            lambda f: np.eye(3) if f.kind == "tensor" else np.ones(f.shape) * (f.kind == "moments")
        )[keep]
        _, _, vt = np.linalg.svd(c[None, :])
        basis = basis @ vt[1:].T  # an orthonormal basis of the trace-preserving directions
    basis = jnp.asarray(basis, dtype)
    jacobian = jax.jacfwd(residual)(flat)
    sensitivity = jnp.linalg.norm(jacobian, axis=0)  # per physical coordinate
    J = jacobian @ basis
    scale = jnp.linalg.norm(J, axis=0)
    dead = scale == 0
    scale = jnp.where(dead, 1.0, scale)
    _, s, vt = jnp.linalg.svd(J / scale, full_matrices=False)
    full_rank = jnp.all(s > config.rtol * s[0]) & ~jnp.any(dead)
    null = jnp.where((s <= config.rtol * s[0])[:, None], vt, 0.0)  # near-null directions, scaled
    null = (null / scale) @ basis.T  # in the physical coordinates
    # Each physical coordinate in units of its own sensitivity; each direction normalised.
    weighted = null * jnp.where(sensitivity > 0, sensitivity, 1.0)
    weighted = weighted / jnp.maximum(
        jnp.linalg.norm(weighted, axis=1, keepdims=True), jnp.finfo(dtype).tiny
    )
    moved = (jnp.max(jnp.abs(weighted), axis=0) > 0.05) | (sensitivity == 0)
    moved = unravel(moved.astype(dtype))
    moved["values"] = [
        (v + v.T) > 0 if f.kind == "tensor" else v > 0
        for f, v in zip(config.fitted, moved["values"])
    ]
    flags = jax.tree.map(lambda x: ~(x > 0), moved)
    condition = jnp.where(full_rank, s[0] / s[-1], jnp.inf)
    return flags, s, condition, full_rank


def _finish_one(config, carry, dynamic, data, h, value, failed, result):
    last = jnp.asarray(len(config.horizons) - 1, jnp.int32)
    values, m0, g0 = config.unpack(carry.params, dynamic, data)
    flags, s, condition, full_rank = _identifiability(config, carry.params, dynamic, data, h)
    optimised = carry.done & (carry.stage == last)
    reason = jnp.select(
        [~jnp.isfinite(value), failed > 0, ~full_rank, optimised, carry.opt.stalled],
        [
            FIT_REASONS.nonfinite,
            FIT_REASONS.failed_samples,
            FIT_REASONS.unidentifiable,
            FIT_REASONS.converged,
            FIT_REASONS.stalled,
        ],
        FIT_REASONS.max_iters,
    ).astype(jnp.int32)
    # `system`, `params`, `identifiable` are assembled outside the compiled function (the
    # user's `where` is not part of the compilation key): here the fitted leaves' values
    # and flags.
    return SystemFit(
        system=dynamic,
        params=values,
        m0=m0,
        g0=g0,
        loss=value,
        loss_history=carry.history,
        failed_history=carry.failed_history,
        failed_samples=failed,
        iterations=carry.it,
        converged=reason == FIT_REASONS.converged,
        reason=reason,
        identifiable=flags["values"],
        identifiable_m0=flags.get("m0"),
        identifiable_g0=flags.get("g0_chart"),
        singular_values=s,
        condition=condition,
        result=result,
    )


# ---- the batch: one loss evaluation per tick, finished bodies leave between rounds ----


@eqx.filter_jit
def _start(config, theta0, dynamic, data, h):
    params = jax.vmap(lambda t, dyn, dat: _initial_params(config, t, dyn, dat, h))(
        theta0, dynamic, data
    )
    n_bodies = jax.tree.leaves(params)[0].shape[0]
    dtype = h.dtype
    return _Carry(
        params=params,
        opt=jax.vmap(config.machine().init)(jax.vmap(_flat)(params)),
        failed=jnp.zeros(n_bodies, jnp.int32),
        stage=jnp.zeros(n_bodies, jnp.int32),
        it=jnp.zeros(n_bodies, jnp.int32),
        history=jnp.full((n_bodies, config.max_iters + 1), jnp.nan, dtype),
        failed_history=jnp.full((n_bodies, config.max_iters + 1), -1, jnp.int32),
        done=jnp.zeros(n_bodies, bool),
        finished=jnp.zeros(n_bodies, bool),
    )


@eqx.filter_jit
def _run(config, n_evals, carry, dynamic, data, h):
    """Up to `n_evals` ticks (until every body is finished if `None`): each evaluates the
    loss and gradient of every body at its trial point in one batched call, then lets each
    body digest its own."""
    machine = config.machine()
    _, unravel = ravel_pytree(jax.tree.map(lambda x: x[0], carry.params))
    horizons = jnp.asarray(config.horizons)
    gradient = jax.value_and_grad(config.batch_loss, has_aux=True)

    def cond(state):
        k, c = state
        more = ~jnp.all(c.finished)
        return more if n_evals is None else more & (k < n_evals)

    def body(state):
        k, c = state
        trial = jax.vmap(unravel)(jax.vmap(machine.trial)(c.opt))
        (_, (value, failed, _)), grad = gradient(trial, dynamic, data, h, horizons[c.stage])
        digest = lambda *a: _digest(config, machine, unravel, *a)
        return k + 1, jax.vmap(digest)(c, value, jax.vmap(_flat)(grad), failed)

    return jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), carry))[1]


@eqx.filter_jit
def _finish(config, carry, dynamic, data, h):
    last = jnp.full(carry.it.shape, config.horizons[-1])
    _, (value, failed, result) = config.batch_loss(carry.params, dynamic, data, h, last)
    return jax.vmap(lambda c, dyn, dat, *rest: _finish_one(config, c, dyn, dat, h, *rest))(
        carry, dynamic, data, value, failed, result
    )


def _bucket(n_active: int, n_total: int) -> int:
    """Compiled batch sizes: the full batch, then powers of 4 (few compilations)."""
    size = 1
    while size < n_active:
        size *= 4
    return min(size, n_total)


def _iterate(config, check_every, carry, dynamic, data, h):
    """Run the optimiser in rounds of `check_every` ticks (`None`: one round to the end);
    after each, the finished bodies leave the batch."""
    if check_every is None:
        return _run(config, None, carry, dynamic, data, h)
    n_total = int(carry.it.shape[0])
    take = lambda tree, idx: jax.tree.map(lambda x: x[idx], tree)
    while True:
        active = np.flatnonzero(~np.asarray(carry.finished))
        if active.size == 0:
            return carry
        size = _bucket(active.size, n_total)
        if size == n_total:
            carry = _run(config, check_every, carry, dynamic, data, h)
            continue
        idx = np.concatenate([active, np.full(size - active.size, active[0])])
        sub = _run(config, check_every, take(carry, idx), take(dynamic, idx), take(data, idx), h)
        sub = take(sub, np.arange(active.size))
        carry = jax.tree.map(lambda full, part, rows=active: full.at[rows].set(part), carry, sub)
