"""Inertia identification: fit a rigid body to observed orientations / angular velocities.

The model is the discrete trajectory itself: `simulate(RigidBody(I), integrator, g₀, Π₀)`
sampled every `sample_every` steps, differentiated end to end (each Newton solve by the
implicit function theorem, `_newton.py`). The loss is the mean over samples of

    w_R ‖g_k − R_k‖_F²  +  w_Ω ‖I⁻¹Π_k − Ω_k‖²,

minimised over unconstrained parameters with optax (L-BFGS with a zoom line search, or
Adam). A parametrisation keeps the inertia symmetric positive definite, and on request
physically realisable (the triangle inequalities `I₁ ≤ I₂ + I₃`, …): the inertia of a mass
distribution with second-moment matrix `Σ = ∫ x xᵀ dm ≻ 0` is `I = tr(Σ)·1 − Σ`; with
`Σ = diag(Λ)` this is the paper's `I₁ = Λ₂ + Λ₃, I₂ = Λ₁ + Λ₃, I₃ = Λ₁ + Λ₂` (§5).

**Gauge.** Scaling `(I, Π₀) ↦ (cI, cΠ₀)` leaves every discrete increment unchanged (the DEP
equation `Π_k = dφ⁻¹(ξ_k)ᵀ I ξ_k/h` is homogeneous of degree one in `(I, Π)`), hence every
orientation `g_k` and every angular velocity `I⁻¹Π_k`. When Π₀ is unknown only `I` up to
scale is observable, and the fit fixes the gauge explicitly: the trace of the inertia is
held at `trace` (default: the trace of the initial guess). With Π₀ known there is no gauge
freedom and the scale is fitted too.

**Failures.** A trial inertia can make a step fail (e.g. a rotation ≥ π in one step). Such
samples are not dropped (that would reward failing) but charged a fixed penalty — the
largest possible orientation error, `‖g − R‖_F² ≤ 8`, and `4 max_k ‖Ω_k‖²` for velocities —
whose gradient is zero; the count of failed samples is reported at every iteration.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float, Int

from ._checks import check_finite, is_concrete
from ._groups._so3 import SO3
from ._integrators._base import AbstractIntegrator
from ._integrators._dep import DEP
from ._simulate import simulate
from ._systems._rigid_body import RigidBody

_ORIENTATION_PENALTY = 8.0  # max ‖g − R‖_F² over rotations g, R


class InertiaFit(eqx.Module):
    """The result of `fit_inertia` (leading batch axes when several bodies were fitted).

    **Attributes:**

    - `inertia`: fitted principal moments `(3,)`, or the tensor `(3, 3)` with `tensor=True`.
    - `m0`, `g0`: the initial momentum and orientation used (fitted if they were unknown).
    - `loss`: final loss; `loss_history`: loss at every iteration, shape `(max_iters + 1,)`,
      NaN after the last iteration taken.
    - `failed_history`: number of failed (penalised) samples at every iteration, −1 after
      the last; `failed_samples`: at the final parameters (0 for a usable fit).
    - `iterations`, `converged` (‖∇loss‖_∞ ≤ `gtol` and no failed sample), `result`: the
      `RESULTS` code of the final simulation.
    """

    inertia: Float[Array, "*batch 3"] | Float[Array, "*batch 3 3"]
    m0: Float[Array, "*batch 3"]
    g0: Float[Array, "*batch 3 3"]
    loss: Float[Array, "*batch"]
    loss_history: Float[Array, "*batch iters"]
    failed_history: Int[Array, "*batch iters"]
    failed_samples: Int[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    result: Int[Array, "*batch"]


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
                + (" and satisfy the strict triangle inequalities I₁ < I₂ + I₃, …" if realisable else "")
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


# ---- the fit --------------------------------------------------------------------------


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
) -> InertiaFit:
    """Fit the inertia (and Π₀, g₀ when unknown) of rigid bodies to observations.

    Sample `k` (`k = 0, …, S − 1`) is taken at step `k·sample_every`, time `k·sample_every·h`.
    Leading batch axes on the observations fit many bodies at once in one compiled call
    (`jax.vmap` of the whole optimisation); the other arrays are shared or carry the same
    batch axes.

    **Arguments:**

    - `orientations`: observed attitudes `R_k ∈ SO(3)`, shape `(*batch, S, 3, 3)` (noisy
      rotation vectors `r_k` become `lievi.SO3.exp(r_k)`).
    - `angular_velocities`: observed body angular velocities `Ω_k = I⁻¹Π_k`, `(*batch, S, 3)`.
      Give at least one of the two.
    - `h`, `sample_every`: step size of the model and steps between samples.
    - `inertia`: initial guess, principal moments `(3,)` (or a tensor `(3, 3)` with `tensor=True`).
    - `m0`: the known initial body momentum, or `None` to fit it (initial guess from the
      first two samples). Then the gauge is fixed by holding the trace of the inertia.
    - `g0`: the known initial orientation, or `None` to fit it (initial guess `R_0`).
    - `tensor`: fit a full SPD tensor (6 parameters) instead of principal moments (3).
    - `realisable`: constrain to physically realisable inertias (triangle inequalities).
    - `trace`: the gauge, used only when `m0 is None`; default the trace of `inertia`.
    - `integrator`: the model integrator (default `DEP()`, exponential chart).
    - `optimizer`: `"lbfgs"` (`optax.lbfgs`, zoom line search), `"adam"` (`optax.adam` at
      `learning_rate`), or any `optax.GradientTransformation` (used as `update(g, s, p)`).
    - `max_iters`, `gtol`: stop when `‖∇loss‖_∞ ≤ gtol` (gradient in the unconstrained
      parameters; default 1e-11 in float64, 1e-4 in float32 — where round-off in a
      400-step simulation already puts the gradient at the optimum near 2e-5) or after
      `max_iters`.
    - `horizons`: continuation in the observed horizon. Over many periods the loss is far
      from convex in the inertia (a wrong inertia puts the trajectory out of phase), so the
      fit first uses only the first `horizons[0]` samples, then the first `horizons[1]`, …,
      each stage started from the previous one's solution and run until
      `‖∇loss‖_∞ ≤ √gtol` (the last stage: `gtol`). Default: 4, 8, 16, … up to `S`. One
      compilation for all stages (the stage only changes a mask).
    - `orientation_weight`, `velocity_weight`: `w_R`, `w_Ω` of the loss: scalars, or one
      weight per sample, shape `(S,)` or `(*batch, S)`. With Gaussian noise of known size
      `σ_k` on sample `k`, `w_k = 1/σ_k²` makes the fit the maximum-likelihood estimate.

    **Returns:** an `InertiaFit`.
    """
    if orientations is None and angular_velocities is None:
        raise ValueError("Give `orientations` and/or `angular_velocities` to fit to.")
    if g0 is None and orientations is None:
        raise ValueError("`g0` is needed when no `orientations` are observed.")
    if isinstance(sample_every, bool) or not isinstance(sample_every, (int, np.integer)) or sample_every < 1:
        raise ValueError(f"`sample_every` must be an integer ≥ 1, got {sample_every!r}.")
    if isinstance(max_iters, bool) or not isinstance(max_iters, (int, np.integer)) or max_iters < 1:
        raise ValueError(f"`max_iters` must be an integer ≥ 1, got {max_iters!r}.")
    if isinstance(optimizer, str) and optimizer not in ("lbfgs", "adam"):
        raise ValueError(f"`optimizer` must be 'lbfgs', 'adam' or an optax transformation, got {optimizer!r}.")

    obs = orientations if orientations is not None else angular_velocities
    obs_core = 3 if orientations is not None else 2
    batch_shape = jnp.shape(obs)[: jnp.ndim(obs) - obs_core]
    n_samples = jnp.shape(obs)[len(batch_shape)]
    if n_samples < 2:
        raise ValueError(f"need at least 2 samples per body, got {n_samples}.")
    if orientations is not None:
        _check_trailing("orientations", orientations, batch_shape, (n_samples, 3, 3))
    if angular_velocities is not None:
        _check_trailing("angular_velocities", angular_velocities, batch_shape, (n_samples, 3))
    inertia_core = (3, 3) if tensor else (3,)
    inertia = _batched("inertia", inertia, batch_shape, inertia_core)
    m0 = None if m0 is None else _batched("m0", m0, batch_shape, (3,))
    g0 = None if g0 is None else _batched("g0", g0, batch_shape, (3, 3))
    trace = None if trace is None else _batched("trace", trace, batch_shape, ())
    weights = []
    for name, w in (("orientation_weight", orientation_weight), ("velocity_weight", velocity_weight)):
        w = jnp.broadcast_to(w, (n_samples,)) if jnp.ndim(w) == 0 else w
        w = _batched(name, w, batch_shape, (n_samples,))
        check_finite(name, w)
        if is_concrete(w) and np.any(np.asarray(w) < 0):
            raise ValueError(f"`{name}` must be ≥ 0.")
        weights.append(w)

    dtype = jnp.result_type(*[x for x in (orientations, angular_velocities, inertia, m0, g0, h) if x is not None], float)
    cast = lambda x: None if x is None else jnp.asarray(x, dtype)  # noqa: E731
    orientations, angular_velocities, m0, g0, trace = map(cast, (orientations, angular_velocities, m0, g0, trace))
    weights = tuple(map(cast, weights))
    if not is_concrete(inertia):
        raise ValueError("`inertia` (the initial guess) must be a concrete array, not traced.")
    check_finite("inertia", inertia)
    theta0 = np.apply_along_axis(
        lambda x: _from_inertia(x.reshape(inertia_core), tensor, realisable),
        -1,
        np.asarray(inertia).reshape(batch_shape + (-1,)),
    )
    if trace is None and m0 is None:
        guess = np.asarray(inertia, float)
        trace = jnp.asarray(np.trace(guess, axis1=-2, axis2=-1) if tensor else guess.sum(-1), dtype)
    if gtol is None:
        # float32: the gradient's round-off floor (≈ 2e-5 at the optimum of a 400-step
        # HLW fit, measured) must lie below the tolerance.
        gtol = 1e-11 if jnp.finfo(dtype).bits >= 64 else 1e-4
    if horizons is None:
        horizons = tuple(min(4 * 2**i, n_samples) for i in range(int(np.ceil(np.log2(max(n_samples / 4, 1)))) + 1))
    horizons = tuple(int(x) for x in horizons)
    if not horizons or horizons[-1] != n_samples or any(b <= a for a, b in zip(horizons, horizons[1:])) or horizons[0] < 2:
        raise ValueError(
            f"`horizons` must increase from ≥ 2 to the number of samples ({n_samples}), got {horizons}."
        )

    static = dict(
        integrator=integrator,
        sample_every=int(sample_every),
        n_samples=int(n_samples),
        tensor=tensor,
        realisable=realisable,
        optimizer=optimizer,
        learning_rate=learning_rate,
        max_iters=int(max_iters),
        gtol=float(gtol),
        horizons=horizons,
    )
    return _run(
        tuple(sorted(static.items())),
        len(batch_shape),
        jnp.asarray(theta0, dtype),
        orientations,
        angular_velocities,
        m0,
        g0,
        trace,
        weights,
        jnp.asarray(h, dtype),
    )


@eqx.filter_jit
def _run(static: tuple, n_batch: int, *args):
    # `static` (hashable: integrator, flags, optimiser) and `n_batch` are compile-time
    # constants, so repeated fits of the same shapes reuse one compilation.
    fit = functools.partial(_fit_one, **dict(static))
    for _ in range(n_batch):  # every argument but h carries the batch axes
        fit = jax.vmap(fit, in_axes=(0, 0, 0, 0, 0, 0, 0, None))
    return fit(*args)


def _check_trailing(name, x, batch_shape, core):
    if tuple(jnp.shape(x)) != tuple(batch_shape) + tuple(core):
        raise ValueError(
            f"`{name}` must have shape {tuple(batch_shape) + tuple(core)} (batch axes, then "
            f"{core}), got {tuple(jnp.shape(x))}."
        )
    check_finite(name, x)


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


def _fit_one(
    theta0,
    orientations,
    angular_velocities,
    m0_known,
    g0_known,
    trace,
    weights,
    h,
    *,
    integrator,
    sample_every,
    n_samples,
    tensor,
    realisable,
    optimizer,
    learning_rate,
    max_iters,
    gtol,
    horizons,
):
    dtype = theta0.dtype
    n_steps = (n_samples - 1) * sample_every
    w_orientation, w_velocity = weights  # per sample, (S,)

    def inertia_of(params):
        inertia = _to_inertia(params["theta"], tensor, realisable)
        if m0_known is None:  # gauge: fix the trace (see the module docstring)
            inertia = inertia * (trace / _trace(inertia))
        return inertia

    def g0_of(params):
        return g0_known if g0_known is not None else orientations[0] @ SO3.exp(params["g0_chart"])

    def m0_of(params):
        return m0_known if m0_known is not None else params["m0"]

    sample_index = jnp.arange(n_samples)

    def loss_terms(params, horizon):
        # optax's zoom line search scales by a float64 step size when x64 is on, which
        # would promote float32 trial points (and the whole simulation) to float64.
        params = jax.tree.map(lambda x: x.astype(dtype), params)
        counted = sample_index < horizon
        inertia = inertia_of(params)
        body = RigidBody(inertia)
        sol = simulate(
            body, integrator, g0_of(params), m0_of(params), h=h, n_steps=n_steps, save_every=sample_every, throw=False
        )
        valid = jnp.all(jnp.isfinite(sol.m), axis=-1)
        counted = counted.astype(dtype)
        total = jnp.zeros((), dtype)
        if orientations is not None:
            # double where: a failed (NaN) sample never enters arithmetic, so no NaN gradient
            g = jnp.where(valid[:, None, None], sol.g, orientations)
            err = jnp.sum((g - orientations) ** 2, axis=(-2, -1))
            weight = w_orientation * counted / jnp.sum(counted)  # weighted mean over this stage
            total = total + jnp.sum(weight * jnp.where(valid, err, _ORIENTATION_PENALTY))
        if angular_velocities is not None:
            m = jnp.where(valid[:, None], sol.m, 0.0)
            omega = jax.vmap(body.velocity)(m)
            omega = jnp.where(valid[:, None], omega, angular_velocities)
            err = jnp.sum((omega - angular_velocities) ** 2, axis=-1)
            penalty = 4 * jnp.max(jnp.sum(angular_velocities**2, axis=-1))
            weight = w_velocity * counted / jnp.sum(counted)
            total = total + jnp.sum(weight * jnp.where(valid, err, penalty))
        return total, (jnp.sum(~valid & (counted > 0)), sol.result)

    # Initial parameters. Unknown Π₀: from the first two samples, Π₀ ≈ I·Ω₀.
    params = {"theta": theta0}
    if m0_known is None:
        inertia0 = inertia_of(params)
        if orientations is not None:
            omega0 = SO3.log(orientations[0].T @ orientations[1]) / (sample_every * h)
        else:
            omega0 = angular_velocities[0]
        params["m0"] = inertia0 @ omega0 if inertia0.ndim == 2 else inertia0 * omega0
    if g0_known is None:
        params["g0_chart"] = jnp.zeros(3, dtype)

    use_lbfgs = isinstance(optimizer, str) and optimizer == "lbfgs"
    if use_lbfgs:
        opt = optax.lbfgs()

        def update(params, state, horizon):
            loss = lambda p: loss_terms(p, horizon)[0]  # noqa: E731
            value, grad = optax.value_and_grad_from_state(loss)(params, state=state)
            updates, state = opt.update(grad, state, params, value=value, grad=grad, value_fn=loss)
            return optax.apply_updates(params, updates), state

    else:
        opt = optax.adam(learning_rate) if isinstance(optimizer, str) else optimizer

        def update(params, state, horizon):
            grad = jax.grad(lambda p: loss_terms(p, horizon)[0])(params)
            updates, state = opt.update(grad, state, params)
            return optax.apply_updates(params, updates), state

    value_grad_aux = jax.value_and_grad(loss_terms, has_aux=True)
    horizon_of = jnp.asarray(horizons)
    last_stage = len(horizons) - 1
    stage_gtol = max(gtol, np.sqrt(gtol)) if len(horizons) > 1 else gtol

    def measure(params, stage):
        (value, (failed, result)), grad = value_grad_aux(params, horizon_of[stage])
        gnorm = jnp.max(jnp.stack([jnp.max(jnp.abs(g)) for g in jax.tree.leaves(grad)]))
        return value, failed.astype(jnp.int32), result, gnorm

    def stage_done(value, failed, gnorm, stage):
        tol = jnp.where(stage == last_stage, gtol, stage_gtol)
        return (gnorm <= tol) & (failed == 0) & jnp.isfinite(value)

    history = jnp.full(max_iters + 1, jnp.nan, dtype)
    failed_history = jnp.full(max_iters + 1, -1, jnp.int32)
    stage = jnp.asarray(0, jnp.int32)
    value, failed, result, gnorm = measure(params, stage)
    init = (
        params,
        opt.init(params),
        stage,
        jnp.asarray(0, jnp.int32),
        history.at[0].set(value),
        failed_history.at[0].set(failed),
        stage_done(value, failed, gnorm, stage),
    )

    def cond(carry):
        _, _, stage, it, _, _, done = carry
        return ~(done & (stage == last_stage)) & (it < max_iters)

    def body(carry):
        params, opt_state, stage, it, history, failed_history, done = carry
        # A finished stage hands its solution to the next, longer horizon (fresh optimiser
        # state: the loss has changed).
        advance = done & (stage < last_stage)
        stage = jnp.where(advance, stage + 1, stage)
        fresh = opt.init(params)
        opt_state = jax.tree.map(lambda a, b: jnp.where(advance, a, b), fresh, opt_state)
        params, opt_state = update(params, opt_state, horizon_of[stage])
        if use_lbfgs:
            # The line search already evaluated loss and gradient at the accepted point.
            value = optax.tree.get(opt_state, "value")
            grad = optax.tree.get(opt_state, "grad")
            gnorm = jnp.max(jnp.stack([jnp.max(jnp.abs(g)) for g in jax.tree.leaves(grad)]))
            failed = loss_terms(params, horizon_of[stage])[1][0].astype(jnp.int32)
        else:
            value, failed, _, gnorm = measure(params, stage)
        it = it + 1
        return (
            params,
            opt_state,
            stage,
            it,
            history.at[it].set(value),
            failed_history.at[it].set(failed),
            stage_done(value, failed, gnorm, stage),
        )

    params, _, stage, iterations, history, failed_history, done = jax.lax.while_loop(cond, body, init)
    converged = done & (stage == last_stage)
    value, failed, result, _ = measure(params, jnp.asarray(last_stage, jnp.int32))
    return InertiaFit(
        inertia=inertia_of(params),
        m0=m0_of(params),
        g0=g0_of(params),
        loss=value,
        loss_history=history,
        failed_history=failed_history,
        failed_samples=failed,
        iterations=iterations,
        converged=converged,
        result=result,
    )

