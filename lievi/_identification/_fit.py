"""System identification: fit chosen parameters of a system to observed orientations /
angular velocities.

The model is the discrete trajectory itself: `simulate(system, integrator, g₀, m₀)` sampled
every `sample_every` steps, differentiated end to end (each Newton solve by the implicit
function theorem, `_newton.py`). The loss is the weighted mean over samples of the squared
residuals

    r_k = ( √w_R (g_k − R_k),  √w_Ω (Ω_k − Ω̂_k) ),     Ω_k = velocity(m_k),

minimised by L-BFGS with a backtracking line search (`_optimizer.py`), or by any optax
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

**Goodness of fit.** A fit whose residuals at the optimum are systematic — lag-one
autocorrelation of the weighted residual sequence above 0.5, where noise gives ≈ 0 — and
whose loss exceeds 1e-6 of the observed motion's weighted size is reported `misfit` (the
data are not this model's motion), or `boundary` when a realisable inertia ends on the
realisability boundary (a local minimum of the constrained problem).

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
a per-body state machine that needs exactly one evaluation per tick (`_optimizer.py`):
a body in its line search and a body starting a new iteration share each evaluation, and
none waits for the longest line search of the batch. Large batches run in rounds of
`check_every` ticks: after each round the bodies that have finished leave the batch and the
others continue in a smaller one.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from .._checks import check_finite, is_concrete
from .._integrators._base import AbstractIntegrator
from .._integrators._dep import DEP
from .._systems._base import AbstractLieSystem
from .._systems._rigid_body import RigidBody
from ._arguments import (
    batch_shape_of,
    batched,
    check_data,
    check_horizons,
    check_options,
    fitted_leaves,
    orientations_from,
)
from ._parametrisation import inertia_parametrisation
from ._problem import Problem, loss_scale
from ._result import SystemFit
from ._schedule import finish, initial_momenta, iterate, start
from ._start import default_inertia


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
    quaternion: str | None = None,
) -> SystemFit:
    """Fit chosen parameters of `system` (and Π₀, g₀ when unknown) to observations.

    Sample `k` (`k = 0, …, S − 1`) is taken at step `k·sample_every`, time `k·sample_every·h`.
    Leading batch axes on the observations fit many bodies at once; the other arrays are
    shared or carry the same batch axes.

    **Arguments:**

    - `system`: the model with the initial guess of the fitted parameters and the known
      values of the others, e.g. `lievi.heavy_top(I_guess, mass, ρ_guess)`.
    - `orientations`: observed attitudes `R_k`, shape `(*batch, S, n, n)` (noisy rotation
      vectors `r_k` become `lievi.SO3.exp(r_k)`); rotations to 1e-6. For a system of
      several bodies each sample is one state of the system, `(*batch, S,
      *element_shape)`: `(*batch, S, N, 4, 4)` for `lievi.RigidBodies`, `(*batch, S, N, 3,
      3)` for `lievi.RigidRotors`.
    - `angular_velocities`: observed velocities `Ω_k = velocity(m_k)` (body angular
      velocities `I⁻¹Π_k` for a rigid body), `(*batch, S, d)`, or `(*batch, S,
      *momentum_shape)` for several bodies. Give at least one of the two.
    - `h`, `sample_every`: step size of the model and steps between samples.
    - `params`: a function selecting the fitted leaves, as `where` of `eqx.tree_at`:
      `lambda s: s.inertia` (default), `lambda s: (s.inertia, s.potential.center_of_mass)`,
      … A rigid body's `inertia` stays positive definite (principal moments `(3,)` or a
      tensor `(3, 3)`, by its shape); other leaves are unconstrained.
    - `m0`: the known initial momentum, or `None` to fit it (initial guess: for a free
      rigid body observed through orientations, `R₀ᵀ` times the mean over the record of
      the conserved spatial momentum `R_{k+½} I ω_{k+½}` of each interval between
      samples; otherwise from the first two samples). Then, if the inertia is fitted, the
      gauge is fixed by its trace.
    - `g0`: the known initial orientation, or `None` to fit it (initial guess `R_0`; one
      body on SO(3) only: a system of several bodies needs `g0`).
    - `system_axis`: `None` (one initial guess for every body) or `0` (every array leaf of
      `system` carries the batch axes first, e.g. `jax.vmap(lievi.RigidBody)(guesses)`).
    - `realisable`: constrain the inertia to physically realisable ones (triangle inequalities).
    - `trace`: the gauge (> 0), used only when it applies; default the trace of the guess.
    - `integrator`: the model integrator (default `DEP()`, exponential chart).
    - `optimizer`: `"lbfgs"` (L-BFGS, memory 10, backtracking line search with the Armijo
      or the approximate Wolfe conditions), `"adam"` (`optax.adam` at `learning_rate`), or
      any `optax.GradientTransformation` (used as `update(g, s, p)`, one loss evaluation per
      iteration).
    - `max_iters`, `gtol`: stop when `‖∇loss‖_∞ ≤ gtol`, the gradient of the loss
      normalised by the weighted size of the observations (`mean_k w_R,k`, plus
      `mean_k w_Ω,k ‖Ω̂_k‖²` for velocities), in the unconstrained parameters, with Π₀ in
      units of its initial guess's norm: relative, so unchanged when the weights are
      scaled (`1/σ²` or 1) or the velocities expressed in other units (the reported losses
      are not normalised); default 1e-11 in float64, 1e-4 in float32 — where round-off in a
      400-step simulation already puts the gradient at the optimum near 2e-5) or after
      `max_iters`.
    - `horizons`: continuation in the observed horizon. Over many periods the loss is far
      from convex in the parameters (a wrong inertia puts the trajectory out of phase), so
      the fit first uses only the first `horizons[0]` samples, then the first
      `horizons[1]`, …, each stage started from the previous one's solution and run until
      `‖∇loss‖_∞ ≤ √gtol` (the last stage: `gtol`). Default: 4, 8, 16, … up to `S`. Each
      body starts at the longest stage over whose samples its initial guess already
      reproduces every observation (`‖g_k − R_k‖_F ≤ 0.5`; velocities within half their
      rms): a start in phase with the whole record skips the short stages, where a few
      noisy samples do not determine the parameters. One compilation for all stages (the
      stage only changes a mask).
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
    - `quaternion`: `None` (orientations are rotation matrices), or `"wxyz"` (scalar
      first) / `"xyzw"` (scalar last, scipy's order): the orientations are quaternions
      `(*batch, S, 4)` in that order. Quaternions without it are refused with a hint.

    **Returns:** a `SystemFit`.
    """
    orientations = orientations_from(orientations, quaternion)
    check_options(
        system=system,
        sample_every=sample_every,
        max_iters=max_iters,
        check_every=check_every,
        optimizer=optimizer,
        learning_rate=learning_rate,
        gtol=gtol,
        identifiability_rtol=identifiability_rtol,
        h=h,
        system_axis=system_axis,
    )
    batch_shape, n_samples, m0, g0, trace, weights = check_data(
        system,
        orientations,
        angular_velocities,
        m0,
        g0,
        trace,
        orientation_weight,
        velocity_weight,
    )
    fitted = fitted_leaves(system, params, batch_shape, system_axis, realisable)
    horizons = check_horizons(horizons, n_samples)

    leaves, treedef = jax.tree.flatten(system)
    dtype = jnp.result_type(
        *[x for x in (orientations, angular_velocities, m0, g0, h) if x is not None],
        *[x for x in leaves if eqx.is_inexact_array(x)],
        float,
    )
    # The system's arrays (and the fitted leaves, whatever their type) become the batched
    # dynamic part; the rest (functions, static fields) is closed over.
    for f in fitted:
        leaves[f.index] = jnp.asarray(leaves[f.index], dtype)
    system = jax.tree.unflatten(treedef, leaves)
    dynamic, static = eqx.partition(system, eqx.is_array)
    if system_axis is None:
        dynamic = jax.tree.map(lambda x: jnp.broadcast_to(x, batch_shape + jnp.shape(x)), dynamic)

    guesses = []  # per fitted leaf, broadcast to the batch
    for f in fitted:
        value = np.asarray(leaves[f.index], float)
        guesses.append(
            np.broadcast_to(value, batch_shape + f.shape) if system_axis is None else value
        )
    theta0 = []
    for f, value in zip(fitted, guesses):
        flat = value.reshape((-1,) + f.shape)
        theta = np.stack([f.from_value(x) for x in flat])
        theta0.append(jnp.asarray(theta.reshape(batch_shape + theta.shape[1:]), dtype))
    inertia = next((i for i, f in enumerate(fitted) if f.is_inertia), None)
    gauge = (
        m0 is None
        and inertia is not None
        and (system.potential is None or any(not f.is_inertia for f in fitted))
    )
    if gauge and trace is None:
        f = fitted[inertia]
        flat = guesses[inertia].reshape((-1,) + f.shape)
        trace = np.reshape([float(f.trace(jnp.asarray(x))) for x in flat], batch_shape)
    trace = jnp.asarray(trace, dtype) if gauge else None

    if gtol is None:
        # float32: the gradient's round-off floor (≈ 2e-5 at the optimum of a 400-step
        # HLW fit, measured) must lie below the tolerance.
        gtol = 1e-11 if jnp.finfo(dtype).bits >= 64 else 1e-4
    if identifiability_rtol is None:
        identifiability_rtol = float(jnp.finfo(dtype).eps) ** (1 / 3)

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
    data["loss_scale"] = jax.vmap(loss_scale)(data)

    problem = Problem(
        static=static,
        fitted=fitted,
        integrator=integrator,
        sample_every=int(sample_every),
        n_samples=n_samples,
        optimizer=optimizer,
        learning_rate=float(learning_rate),
        max_iters=int(max_iters),
        gtol=float(gtol),
        horizons=horizons,
        rtol=float(identifiability_rtol),
    )
    h = jnp.asarray(h, dtype)
    m0_guess = None
    if data["m0"] is None:
        m0_guess = initial_momenta(problem, theta0, dynamic, data, h)
        # The norm of each run's whole momentum (every body's, for a system of several).
        size = jnp.linalg.norm(m0_guess.reshape(n_bodies, -1), axis=-1)
        size = jnp.where(size > 0, size, 1.0)
        data["momentum_scale"] = size.reshape((n_bodies,) + (1,) * (m0_guess.ndim - 1))
    carry = start(problem, theta0, m0_guess, dynamic, data, h)
    if check_every is None and n_bodies >= 64:
        check_every = 20
    carry = iterate(problem, check_every, carry, dynamic, data, h)
    out = finish(problem, carry, dynamic, data, h)
    out = jax.tree.map(lambda x: jnp.reshape(x, batch_shape + jnp.shape(x)[1:]), out)
    fitted_system = _replace_leaves(fitted, eqx.combine(out.system, static), out.params)
    flag_tree = _replace_leaves(fitted, eqx.combine(out.system, static), out.identifiable)
    return eqx.tree_at(
        lambda f: (f.system, f.params, f.identifiable),
        out,
        (fitted_system, params(fitted_system), params(flag_tree)),
        is_leaf=lambda x: x is None,
    )


def _replace_leaves(fitted, system, values):
    leaves, treedef = jax.tree.flatten(system)
    for f, v in zip(fitted, values):
        leaves[f.index] = v
    return jax.tree.unflatten(treedef, leaves)


def fit_inertia(
    orientations: Float[Array, "*batch S 3 3"] | None = None,
    angular_velocities: Float[Array, "*batch S 3"] | None = None,
    *,
    inertia=None,
    tensor: bool = False,
    **options,
) -> SystemFit:
    """Fit the inertia (and Π₀, g₀ when unknown) of free rigid bodies to observations.

    `fit_system(lievi.RigidBody(inertia), …, params=lambda s: s.inertia)`; see `fit_system`
    for every other argument (all keyword arguments of `fit_system` but `params` and
    `system_axis` are accepted) and the report.

    **Arguments** (beyond `fit_system`'s):

    - `inertia`: initial guess, principal moments `(3,)` (or a tensor `(3, 3)` with
      `tensor=True`), shared or one per body `(*batch, 3)`. Default `None`: estimated from
      the observations, per body, by linear least squares (the spatial angular momentum
      `g I ω` is conserved, with `ω` from finite differences of the orientations; from
      angular velocities, Euler's equations), scaled to the trace 3; where the data do not
      determine it (a spin about a principal axis, a body at rest) or it is not positive
      definite (realisable), the equal moments `(1, 1, 1)`.
    - `tensor`: fit a full SPD tensor (6 parameters) instead of principal moments (3).

    **Returns:** a `SystemFit` (`fit.inertia` is the fitted inertia).
    """
    for name in ("system", "params", "system_axis"):
        if name in options:
            raise TypeError(f"fit_inertia() got an unexpected keyword argument {name!r}")
    orientations = orientations_from(orientations, options.pop("quaternion", None))
    batch_shape = batch_shape_of(orientations, angular_velocities)
    core = (3, 3) if tensor else (3,)
    realisable = bool(options.get("realisable", False))
    if inertia is None:
        inertia = _default_inertia(orientations, angular_velocities, batch_shape, tensor, options)
        observed = orientations if orientations is not None else angular_velocities
        if jnp.issubdtype(jnp.result_type(observed), jnp.floating):
            inertia = np.asarray(inertia, jnp.result_type(observed))  # float32 data: float32
    inertia = batched("inertia", inertia, batch_shape, core)
    if not is_concrete(inertia):
        raise ValueError("`inertia` (the initial guess) must be a concrete array, not traced.")
    check_finite("inertia", inertia)
    parametrisation = inertia_parametrisation(0, core, realisable)
    for x in np.asarray(inertia, float).reshape((-1,) + core):
        parametrisation.from_value(x)  # the guess's own error message first
    if jnp.shape(inertia) == core:
        system, axis = RigidBody(jnp.asarray(inertia)), None  # the guess's own dtype
    else:
        make = RigidBody
        for _ in batch_shape:
            make = jax.vmap(make)
        system, axis = make(jnp.asarray(inertia)), 0
    return fit_system(
        system,
        orientations,
        angular_velocities,
        params=lambda s: s.inertia,
        system_axis=axis,
        **options,
    )


def _default_inertia(orientations, angular_velocities, batch_shape, tensor, options):
    """`default_inertia` where the arguments it needs are usable (else `(1, 1, 1)`:
    `fit_system` reports what is wrong with them)."""
    fallback = np.eye(3) if tensor else np.ones(3)
    h, every, m0 = options.get("h"), options.get("sample_every"), options.get("m0")
    usable = (
        is_concrete(h)
        and jnp.ndim(h) == 0
        and isinstance(every, (int, np.integer))
        and np.isfinite(float(h))
        and float(h) * every > 0
        and (m0 is None or (is_concrete(m0) and jnp.shape(m0) in ((3,), batch_shape + (3,))))
        and all(x is None or is_concrete(x) for x in (orientations, angular_velocities))
    )
    if orientations is not None:
        usable = usable and jnp.shape(orientations)[len(batch_shape) :][1:] == (3, 3)
        angular_velocities = None
    else:
        usable = usable and jnp.shape(angular_velocities)[len(batch_shape) :][1:] == (3,)
    if not usable:
        return fallback
    return default_inertia(
        orientations,
        angular_velocities,
        float(h) * every,
        None if m0 is None else np.asarray(m0, float),
        tensor,
        bool(options.get("realisable", False)),
    )


def _inertia_signature():
    """`fit_inertia`'s signature: its own arguments and `fit_system`'s keywords, with
    `inertia` in place of `params` and `tensor` in place of `system_axis`."""
    own = inspect.signature(fit_inertia, eval_str=False).parameters
    replace = {"params": own["inertia"], "system_axis": own["tensor"]}
    parameters = [own["orientations"], own["angular_velocities"]]
    for name, p in inspect.signature(fit_system, eval_str=False).parameters.items():
        if p.kind is inspect.Parameter.KEYWORD_ONLY:
            parameters.append(replace.get(name, p))
    return inspect.Signature(parameters, return_annotation="SystemFit")


fit_inertia.__signature__ = _inertia_signature()
