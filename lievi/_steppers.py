"""What the one step loop (`lievi._loop`) steps: a batch of bodies (one body is a batch of
one), by the integrator's structure-of-arrays kernel (`KernelStepper`, one array per
component of the state, the batch minor) or by the method's own `cached_step` under
`jax.vmap` (`VmapStepper`: every method on every system, forced runs included). A stepper
is built inside the run's program for its `h`, `t0` and initial state (per-run constants
once, outside the loop); the stepper masks a failed body in its own state's layout
(`kept`: one `where` a leaf)."""

from __future__ import annotations

import abc
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import drifts_off_group, input_valid
from ._results import RESULTS
from ._solution import advected_of


class AbstractStepper(eqx.Module):
    """One step of a batch, as the loop runs it (diffrax's `init`/`step` in spirit)."""

    @abc.abstractmethod
    def init(self, g0, m0):
        """The state before the first step (every leaf `(B, …)`)."""

    @abc.abstractmethod
    def step(self, state, data, k, alive):
        """`(state, code, iterations, residual)` after step `k` (`data`: the forcing's data
        of the step; `alive` `(B,)`: the bodies not yet failed); `code` is checked as
        every method's (`RESULTS.checked`)."""

    def settle(self, state):
        """The state at a save (e.g. put back on the group in low precision)."""
        return state

    def kept(self, ok, new, old):
        """`new` for the bodies where `ok` `(B,)`, else `old`: by default every leaf with
        the batch leading."""
        return where_ok(ok, new, old)

    @abc.abstractmethod
    def stored(self, state, save, ok) -> dict:
        """What a save stores of `state` (`save`: a `lievi.Save`): `g` `(B, n, n)`,
        `m`/`advected` `(B, ·)`, NaN where `ok` `(B,)` is false."""

    @abc.abstractmethod
    def advected_at(self, g0):
        """The advected parameter `Γ` `(B, k)` at the elements `g0`, or `None`."""

    @abc.abstractmethod
    def configuration(self, state):
        """`(g, m)` of the state, batch-major `(B, n, n)`, `(B, d)`."""


def where_ok(ok, new, old):
    """`new` where the body is still successful, else `old` (every leaf `(B, …)`)."""

    def pick(x, y):
        return jnp.where(ok.reshape(ok.shape + (1,) * (jnp.ndim(x) - 1)), x, y)

    return jax.tree.map(pick, new, old)


def _finite(state):
    """Whether every component is finite, per body: the leaves of a kernel's state `(B,)`
    or `(k, B)` (one array of components, reduced in one operation)."""
    finite = jnp.asarray(True)
    for x in jax.tree.leaves(state):
        finite = finite & jnp.all(jnp.isfinite(x), axis=tuple(range(jnp.ndim(x) - 1)))
    return finite


class KernelStepper(AbstractStepper):
    """The integrator's kernel: the state is `(entries of g, components of m)` in the
    kernel's layout (`carried`, `carried_momentum`): a tuple of arrays `(B,)` or one array
    `(k, B)`, the batch last either way."""

    kernel: Any
    params: Any
    rates: Any
    bound: float = eqx.field(static=True)
    group: Any = eqx.field(static=True)

    def init(self, g0, m0):
        return self.kernel.carried(g0), self.kernel.carried_momentum(m0)

    def step(self, state, data, k, alive):
        g, m = state
        g_next, m_next, code, iterations, residual = self.kernel.step(self.params, g, m, alive)
        # (h|ω|)² > bound², as h|ω| > bound but for rounding at the bound: no division or
        # square root per body-step.
        too_large = self.kernel.turn_squared(self.rates, m) > self.bound * self.bound
        code = RESULTS.checked(code, _finite((g_next, m_next)), too_large)
        return (g_next, m_next), code, iterations, residual

    def kept(self, ok, new, old):
        # The batch last: `ok` `(B,)` broadcasts against `(B,)` and `(k, B)`.
        return jax.tree.map(lambda x, y: jnp.where(ok, x, y), new, old)

    def settle(self, state):
        if self.group is None:
            return state
        # (k, B) entries → (B, n, n) elements → projected → the kernel's entries.
        elements = self.group.project(self.kernel.elements(jnp.stack(state[0])[None])[:, 0])
        return self.kernel.carried(elements), state[1]

    def stored(self, state, save, ok):
        out = {}
        if save.g:
            out["g"] = self.kernel.elements(jnp.stack(state[0])[None])[:, 0]
        if save.m:
            out["m"] = jnp.stack(state[1], axis=-1)
        advected = self.kernel.advected(state[0]) if save.with_advected() else None
        if advected is not None:
            out["advected"] = jnp.stack(advected, axis=-1)
        return {name: where_ok(ok, x, jnp.full_like(x, jnp.nan)) for name, x in out.items()}

    def advected_at(self, g0):
        advected = self.kernel.advected(self.kernel.carried(g0))
        return None if advected is None else jnp.stack(advected, -1)

    def configuration(self, state):
        g = self.kernel.elements(jnp.stack(state[0])[None])[:, 0]
        return g, jnp.stack(state[1], axis=-1)


class VmapStepper(AbstractStepper):
    """The method's own `cached_step` under `jax.vmap`; the state is `(g, m, cache)`."""

    system: Any
    integrator: Any
    h: Any
    t0: Any
    forcing: Any
    args: Any
    # In-axes of (system, integrator, h, forcing, per-step data): not arrays, never traced.
    axes: Any = eqx.field(static=True)

    def init(self, g0, m0):
        system_axes, integrator_axes, _, _, _ = self.axes
        cache = eqx.filter_vmap(
            lambda system, integrator, g: integrator.step_cache(system, g),
            in_axes=(system_axes, integrator_axes, 0),
        )(self.system, self.integrator, g0)
        return g0, m0, cache

    def step(self, state, data, k, alive):
        forcing, args, t0 = self.forcing, self.args, self.t0

        def one(system, integrator, g, m, h, cache, forcing, data):
            force = None if forcing is None else forcing.at_step(data, args)
            g1, m1, info, cache1 = integrator.cached_step(system, g, m, h, cache, force, t0 + k * h)
            finite = jnp.all(jnp.isfinite(g1)) & jnp.all(jnp.isfinite(m1))
            too_large = integrator.step_too_large(system, m, h)
            code = RESULTS.checked(info.result, finite, too_large)
            return (g1, m1, cache1), code, info.iterations, info.residual

        system_axes, integrator_axes, h_axis, forcing_axes, data_axes = self.axes
        in_axes = (system_axes, integrator_axes, 0, 0, h_axis, 0, forcing_axes, data_axes)
        g, m, cache = state
        return eqx.filter_vmap(one, in_axes=in_axes)(
            self.system, self.integrator, g, m, self.h, cache, forcing, data
        )

    def settle(self, state):
        g = state[0]
        if drifts_off_group(g.dtype):
            # Low precision: the saved state, from which a run may be continued, is kept on
            # the group (to `membership_tolerance`), as is the state carried on.
            return (self.system.group.project(g), *state[1:])
        return state

    def stored(self, state, save, ok):
        out = {}
        if save.g:
            out["g"] = state[0]
        if save.m:
            out["m"] = state[1]
        advected = self._advected(state[0]) if save.with_advected() else None
        if advected is not None:
            out["advected"] = advected
        return {name: where_ok(ok, x, jnp.full_like(x, jnp.nan)) for name, x in out.items()}

    def _advected(self, g):
        potential = self.system.potential
        if potential is None or potential.advected_direction() is None:
            return None
        return jax.vmap(advected_of, in_axes=(self.axes[0], 0))(self.system, g)

    def advected_at(self, g0):
        return self._advected(g0)

    def configuration(self, state):
        return state[0], state[1]


class AbstractPlan(eqx.Module):
    """How a run steps, decided on the host: `stepper` builds the stepper inside the run's
    program; `valid` is the traced input check per body."""

    system: Any
    system_axis: int | None = eqx.field(static=True)

    @abc.abstractmethod
    def stepper(self, g0, m0, h, t0) -> AbstractStepper: ...

    def h_axis(self, h):
        return None if jnp.ndim(h) == 0 else 0

    def valid(self, g0, m0, h, t0, parameters: bool = True):
        in_axes = (self.system.batch_axes(self.system_axis), 0, 0, self.h_axis(h), None)
        check = functools.partial(input_valid, parameters=parameters)
        return jax.vmap(check, in_axes=in_axes)(self.system, g0, m0, h, t0)

    def per_step(self):
        """The forcing's per-step data with the step axis leading, or `None`."""
        return None

    def invariants(self, monitor, g, m):
        """`monitor.invariant` of every body, `(B, k)`."""
        axes = self.system.batch_axes(self.system_axis)
        return jax.vmap(monitor.invariant, in_axes=(axes, 0, 0))(self.system, g, m)


class KernelPlan(AbstractPlan):
    kernel: Any
    constants: Any
    bound: float = eqx.field(static=True)
    project: bool = eqx.field(static=True)

    def stepper(self, g0, m0, h, t0):
        dtype = m0.dtype
        constants = jax.tree.map(lambda x: jnp.asarray(x, dtype), self.constants)
        constants = self.kernel.constants(constants)
        group = self.system.group if self.project and drifts_off_group(dtype) else None
        return KernelStepper(
            self.kernel,
            self.kernel.prepare_run(constants, m0, h),
            # Per-run constants of the step-size check, once outside the loop.
            self.kernel.turn_rates(constants, h),
            self.bound,
            group,
        )


class VmapPlan(AbstractPlan):
    integrator: Any
    forcing: Any = None
    args: Any = None

    def _forcing_axes(self):
        if self.forcing is None:
            return None, None
        return self.forcing.batch_axes(self.system), self.forcing.per_step_axes(self.system)

    def stepper(self, g0, m0, h, t0):
        system_axes = self.system.batch_axes(self.system_axis)
        h_axis = self.h_axis(h)
        # Per-run state (e.g. a preprocessed method's modified moments for this `h`), per
        # body from its own `m0`; every array leaf of the result carries the batch.
        integrator = eqx.filter_vmap(
            lambda system, m0, h: self.integrator.init(system, m0, h),
            in_axes=(system_axes, 0, h_axis),
        )(self.system, m0, h)
        integrator_axes = eqx.if_array(0)
        forcing_axes, data_axes = self._forcing_axes()
        axes = (system_axes, integrator_axes, h_axis, forcing_axes, data_axes)
        return VmapStepper(self.system, integrator, h, t0, self.forcing, self.args, axes)

    def per_step(self):
        if self.forcing is None:
            return None
        _, data_axes = self._forcing_axes()
        data = self.forcing.per_step()
        # Per-body data `(B, n_steps, …)` → `(n_steps, B, …)`: scanned over by step.
        return jax.tree.map(
            lambda x, axis: x if axis is None else jnp.moveaxis(x, 1, 0),
            data,
            data_axes,
            is_leaf=lambda x: x is None,
        )


def plan_for(
    system,
    integrator,
    system_axis,
    forcing=None,
    args=None,
    *,
    tuning=None,
    one_body=False,
    carry_g=True,
):
    """How a run of `integrator` on `system` steps: on the integrator's kernel for it
    (`AbstractIntegrator.batch_kernel`; never forced), else by its own step under
    `jax.vmap`. `tuning`: a `lievi.advanced.Tuning` (`None`: its defaults); `one_body`:
    the kernel as it runs one body; `carry_g=False`: the kernel's reduced form, if any.

    `Tuning(fast=False)` steps every body as a one-body `simulate` steps it, as under
    `jax.vmap` of `simulate`: the kernel as it runs one body (`one_body`), its per-run
    constants once, its state in its own layout. Not the
    method's `step` under `jax.vmap`: there the kernel split `g` into components and
    prepared its constants at every step, and reverse mode assembled each component's
    cotangent in a fusion of its own that recomputed the step (`RK4`'s batched gradient,
    409 bodies: 11× its kernel's)."""
    batched = system_axis is not None
    fast, fixed = (True, None) if tuning is None else (tuning.fast, tuning.fixed_iterations)
    kernel = None
    if forcing is None:
        kernel = integrator.batch_kernel(system, batched)
    if kernel is None:
        return VmapPlan(system, system_axis, integrator, forcing, args)
    constants = kernel.physics(system, batched)
    if not carry_g:
        kernel = kernel.reduced() or kernel
    if fast and fixed is not None:
        kernel = kernel.with_fixed_iterations(fixed)
    elif one_body or not fast:
        # The kernel's one-body form (`AbstractBatchKernel.one_body`; SE(3): a dense step,
        # a fraction of the batch's program).
        kernel = kernel.one_body()
    return KernelPlan(system, system_axis, kernel, constants, integrator.step_bound(), carry_g)
