"""The fitting problem of one body (vmapped over the batch): the model, the residuals,
the loss and its normalisation, the initial point, and the goodness-of-fit test.

The loss the optimiser sees is normalised per body by `data["loss_scale"]`, the weighted
size of the observations (`mean_k w_R,k` for orientations, `mean_k w_Ω,k ‖Ω̂_k‖²` for
angular velocities), and the fitted initial momentum is optimised in units of its initial
guess's norm (`data["momentum_scale"]`). So the stopping test `‖∇loss‖_∞ ≤ gtol` does not
change when the weights are multiplied by a constant (e.g. `1/σ²` instead of 1) or the
momenta and velocities are expressed in other units. The losses reported are not
normalised.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._groups._so3 import SO3
from .._integrators._base import AbstractIntegrator
from .._save import Save
from .._simulate import simulate
from .._simulate_batch import simulate_batch
from .._systems._base import AbstractLieSystem
from .._systems._rigid_body import RigidBody
from ._optimizer import LBFGS, OptaxMachine

ORIENTATION_PENALTY = 8.0  # max ‖g − R‖_F² over rotations g, R

# The goodness-of-fit test: the residuals are "systematic" when their lag-one
# autocorrelation (pooled over components) exceeds this; a noise residual has ≈ 0 (±1/√N)...
MISFIT_CORRELATION = 0.5
# ... and only a loss above this fraction of the observed motion's (weighted) size is
# tested: below it the model reproduces the data to 0.1 % whatever the pattern.
MISFIT_FLOOR = 1e-6

# The horizon stages a fit starts with: the longest stage over whose samples the initial
# guess already reproduces every observation to this (orientations: ‖g_k − R_k‖_F, a
# rotation of about 0.35 rad; velocities: relative to their rms). A start that is in phase
# with the whole record skips the short stages, where a few noisy samples do not determine
# the parameters and the fit can wander off before the longer horizons pin it down.
PREDICTED = 0.5


class Problem(eqx.Module):
    """Everything static about a fit (hashable: one compilation per configuration)."""

    static: AbstractLieSystem = eqx.field(static=True)
    fitted: tuple = eqx.field(static=True)  # a `Parametrisation` per fitted leaf
    integrator: AbstractIntegrator = eqx.field(static=True)
    sample_every: int = eqx.field(static=True)
    n_samples: int = eqx.field(static=True)
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
            value = f.to_value(t)
            if data["trace"] is not None:  # the gauge (see `fit_system`)
                value = f.gauge(value, data["trace"])
            values.append(value)
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
        """One body: weighted residuals per sample `(S, c)`, failed-sample penalty, count
        of failed samples, result."""
        sol = simulate(
            system,
            self.integrator,
            g0,
            m0,
            h=h,
            n_steps=self.n_steps,
            save=Save(every=self.sample_every),
            throw=False,
        )
        return (*self.residual_terms(system, sol.g, sol.m, data, horizon), sol.result)

    def residual_terms(self, system, g, m, data, horizon):
        """Weighted residuals per sample `(S, c)`, failed-sample penalty and count of failed
        samples of one body's simulated samples `g`, `m`."""
        dtype = m.dtype
        S = self.n_samples
        # A sample is one state of the system: every axis after the first (one body's
        # `(n, n)`, `(d,)`; several bodies' `(N, n, n)`, `(N, d)`) is flattened.
        valid = jnp.all(jnp.isfinite(m.reshape(S, -1)), axis=-1) & jnp.all(
            jnp.isfinite(g.reshape(S, -1)), axis=-1
        )
        counted = (jnp.arange(S) < horizon).astype(dtype)
        parts, penalty = [], jnp.zeros((), dtype)
        w_orientation, w_velocity = data["weights"]
        if data["orientations"] is not None:
            R = data["orientations"]
            # double where: a failed (NaN) sample never enters arithmetic, so no NaN gradient
            g = jnp.where(_per_sample(valid, g), g, R)
            weight = w_orientation * counted / jnp.sum(counted)  # weighted mean over this stage
            parts.append(jnp.sqrt(weight)[:, None] * (g - R).reshape(S, -1))
            penalty = penalty + jnp.sum(jnp.where(valid, 0.0, weight * ORIENTATION_PENALTY))
        if data["angular_velocities"] is not None:
            W = data["angular_velocities"]
            m = jnp.where(_per_sample(valid, m), m, 0.0)
            omega = jnp.where(_per_sample(valid, W), jax.vmap(system.velocity)(m), W)
            weight = w_velocity * counted / jnp.sum(counted)
            parts.append(jnp.sqrt(weight)[:, None] * (omega - W).reshape(S, -1))
            worst = 4 * jnp.max(jnp.sum((W**2).reshape(S, -1), axis=-1))
            penalty = penalty + jnp.sum(jnp.where(valid, 0.0, weight * worst))
        failed = jnp.sum(~valid & (counted > 0)).astype(jnp.int32)
        return jnp.concatenate(parts, axis=-1), penalty, failed

    def unpack(self, params, dynamic, data):
        values = self.leaf_values(params["theta"], data)
        m0 = data["m0"] if data["m0"] is not None else params["m0"] * data["momentum_scale"]
        g0 = (
            data["g0"]
            if data["g0"] is not None
            else data["orientations"][0] @ SO3.exp(params["g0_chart"])
        )
        return values, m0, g0

    def batch_loss(self, params, dynamic, data, h, horizon):
        """Every body's loss at once, through `simulate_batch` (its structure-of-arrays fast
        path and that path's reverse mode where the system and integrator have one).

        **Returns:** `(Σ normalised losses, (normalised losses, losses, failed, result,
        residuals))`: the bodies are independent, so the gradient of the sum is every
        body's own gradient."""
        systems, sol = self.rollout(params, dynamic, data, h)
        in_axes = (systems.batch_axes(0), 0, 0, 0, 0)
        r, penalty, failed = jax.vmap(self.residual_terms, in_axes)(
            systems, sol.g, sol.m, data, horizon
        )
        losses = jnp.sum(r**2, axis=(-2, -1)) + penalty
        normalised = losses / data["loss_scale"]
        return jnp.sum(normalised), (normalised, losses, failed, sol.result, r)

    def rollout(self, params, dynamic, data, h):
        """`(systems, solution)`: every body's system at `params` and its trajectory, sampled
        at the observations (`simulate_batch`, its fast path where there is one)."""
        params = jax.tree.map(lambda x: x.astype(h.dtype), params)
        values, m0, g0 = jax.vmap(self.unpack)(params, dynamic, data)
        # `filter_vmap`: a leaf that is not an array (a potential given as a Python
        # function) is the same for every body and stays one leaf, which `jax.vmap`
        # cannot return.
        systems = eqx.filter_vmap(self.system_of)(values, dynamic)
        sol = simulate_batch(
            systems,
            self.integrator,
            g0,
            m0,
            h=h,
            n_steps=self.n_steps,
            save=Save(g=True, m=True, stats=False, every=self.sample_every),
            system_axis=0,
            throw=False,
        )
        return systems, sol

    def predicted(self, params, dynamic, data, h):
        """Per body and sample, whether the model at `params` reproduces the observation
        to within `PREDICTED` (orientations: `‖g_k − R_k‖_F`; velocities: `‖Ω_k − Ω̂_k‖`
        relative to the rms observed velocity; samples of weight 0 count as reproduced),
        `(bodies, S)`."""
        systems, sol = self.rollout(params, dynamic, data, h)
        ok = jnp.ones(sol.m.shape[:2], bool)
        flat = lambda x: x.reshape(*x.shape[:2], -1)  # (bodies, S, one state's entries)
        if data["orientations"] is not None:
            error = jnp.sqrt(jnp.sum(flat((sol.g - data["orientations"]) ** 2), axis=-1))
            ok = ok & ((error <= PREDICTED) | (data["weights"][0] == 0))
        if data["angular_velocities"] is not None:
            W = data["angular_velocities"]
            per_body = jax.vmap(lambda s, m: s.velocity(m), (None, 0))
            omega = jax.vmap(per_body, (systems.batch_axes(0), 0))(systems, sol.m)
            rms = jnp.sqrt(jnp.mean(jnp.sum(flat(W**2), axis=-1), axis=-1, keepdims=True))
            error = jnp.sqrt(jnp.sum(flat((omega - W) ** 2), axis=-1))
            close = error <= PREDICTED * jnp.where(rms > 0, rms, 1.0)
            ok = ok & (close | (data["weights"][1] == 0))
        return ok  # (NaN compares False: a failed sample is not predicted)

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

    def stage_done(self, value, failed, gnorm, stage):
        last = len(self.horizons) - 1
        tol = jnp.where(stage == last, self.gtol, self.stage_gtol)
        return (gnorm <= tol) & (failed == 0) & jnp.isfinite(value)


def _per_sample(flags, x):
    """`flags` `(S,)` shaped to broadcast against `x` `(S, …)`: one flag per sample."""
    return flags.reshape(flags.shape + (1,) * (x.ndim - 1))


def loss_scale(data):
    """One body's loss normaliser: the weighted size of its observations (1 when zero)."""
    w_orientation, w_velocity = data["weights"]
    scale = jnp.zeros((), w_orientation.dtype)
    if data["orientations"] is not None:
        scale = scale + jnp.mean(w_orientation)
    if data["angular_velocities"] is not None:
        W = data["angular_velocities"]
        scale = scale + jnp.mean(w_velocity * jnp.sum((W**2).reshape(W.shape[0], -1), axis=-1))
    return jnp.where(scale > 0, scale, 1.0)


def motion_size(data):
    """One body's weighted mean squared distance of the observations from their first
    (orientations) or mean (velocities) sample: the size of the observed motion."""
    w_orientation, w_velocity = data["weights"]
    n = w_orientation.shape[0]
    size = jnp.zeros((), w_orientation.dtype)
    if data["orientations"] is not None:
        R = data["orientations"]
        size = size + jnp.sum(w_orientation * jnp.sum(((R - R[0]) ** 2).reshape(n, -1), -1)) / n
    if data["angular_velocities"] is not None:
        W = data["angular_velocities"]
        size = size + jnp.sum(w_velocity * jnp.sum(((W - W.mean(0)) ** 2).reshape(n, -1), -1)) / n
    return size


def initial_momentum(problem, theta0, dynamic, data, h):
    """Π₀'s initial guess (unknown Π₀).

    A free rigid body observed through its orientations conserves its spatial angular
    momentum `L = g Π`: every interval between samples gives `L ≈ R_{k+½} I ω_{k+½}` (the
    body velocity `ω_{k+½} = log(R_kᵀ R_{k+1})/Δt` at the midpoint attitude `R_{k+½}`), and
    `Π₀ = R₀ᵀ L̄` with `L̄` their weighted mean over the whole record (the noise of one
    difference, `√2 σ/Δt`, averaged out). Otherwise `Π₀ ≈ legendre(Ω₀)` from the first two
    samples (or the first observed velocity): `Ω₀ = log(R₀⁻¹R₁)/Δt` in the system's group,
    each body's for a system of several."""
    values = problem.leaf_values(theta0, data)
    system = problem.system_of(values, dynamic)
    dt = problem.sample_every * h
    if data["orientations"] is not None:
        R = data["orientations"]
        if isinstance(system, RigidBody) and system.potential is None:
            xi = jax.vmap(SO3.log)(jnp.swapaxes(R[:-1], -1, -2) @ R[1:])
            mid = R[:-1] @ jax.vmap(SO3.exp)(xi / 2)
            spatial = jnp.einsum("kij,kj->ki", mid, jax.vmap(system.legendre)(xi / dt))
            w = data["weights"][0]
            w = w[:-1] * w[1:] / jnp.where(w[:-1] + w[1:] > 0, w[:-1] + w[1:], 1.0)
            w = jnp.where(jnp.sum(w) > 0, w, 1.0)
            L = jnp.sum(w[:, None] * spatial, axis=0) / jnp.sum(w)
            return (R[0].T @ L).astype(h.dtype)
        group = system.group
        omega0 = group.log(group.compose(group.inverse(R[0]), R[1])) / dt
    else:
        omega0 = data["angular_velocities"][0]
    return system.legendre(omega0).astype(h.dtype)


def initial_params(theta0, m0_guess, data):
    """The optimiser's starting point: θ, Π₀ in units of `momentum_scale`, g₀'s chart."""
    params = {"theta": list(theta0)}
    if data["m0"] is None:
        params["m0"] = m0_guess / data["momentum_scale"]
    if data["g0"] is None:
        params["g0_chart"] = jnp.zeros(3, theta0[0].dtype)
    return params


def misfit(residuals, loss, data):
    """Whether one body's residuals `(S, c)` at the solution are systematic rather than
    noise (see the constants above)."""
    tiny = jnp.finfo(residuals.dtype).tiny
    lagged = jnp.sum(residuals[1:] * residuals[:-1])
    correlation = lagged / jnp.maximum(jnp.sum(residuals**2), tiny)
    return (correlation > MISFIT_CORRELATION) & (loss > MISFIT_FLOOR * motion_size(data))
