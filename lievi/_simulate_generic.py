"""`simulate`'s generic loop: the integrator's own `step`, one body at a time.

For what has no structure-of-arrays kernel (`AbstractIntegrator.batch_kernel`) and for
forced runs. Under a transformation (or with a forcing, whose data and closures may be
traced) the run is one static checkpointed `lax.scan`; an eager call runs blocks of saves
by one compiled program whatever `n_steps` and `save_every` (`lievi._horizon`). Both
loops share the step, its checks, the failure record and what is saved.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from ._checks import drifts_off_group
from ._compile import RunProgram, bodies_of, bodies_per_system, once_per_call
from ._horizon import as_count, block_saves, join_blocks, run_blocks, save_buffers, store
from ._newton import ROOT_NAME
from ._progress import AbstractProgressMeter, NoProgressMeter
from ._results import RESULTS
from ._scan import scan_in_segments
from ._solution import Solution, advected_of


def checked_step_result(integrator, system, m, h, g_next, m_next, result):
    """The step's own code, completed by the checks every method gets: a non-finite `g`
    or `m` is `nonfinite` (not only the momentum: a NaN attitude is caught too), and a
    step beyond `integrator.step_bound()` is `step_too_large`, whatever the solve said."""
    finite = jnp.all(jnp.isfinite(g_next)) & jnp.all(jnp.isfinite(m_next))
    return RESULTS.checked(result, finite, integrator.step_too_large(system, m, h))


def _stepper(system, integrator, h, t0, n_steps, progress, forcing, args):
    """One step of the run with its checks and failure record, `(carry, data) → (carry,
    (iterations, residual))`, `carry = (g, m, result, failed_step, k, cache)` (both
    loops; `cache`: what the next step takes over, `AbstractIntegrator.step_cache`)."""

    # Reverse mode keeps each step's input state, the roots of its implicit solves
    # (tagged `ROOT_NAME`: the kernels' and `newton_solve`'s) and its survival mask, and
    # recomputes the rest of the step in the backward pass. Storing every intermediate
    # the linearised step reads instead (for `RigidBodies` with DEP, 177 arrays a step:
    # the SE(3) kernel's closed forms on scalars and the coupling's autodiff force) made
    # a gradient cost 58–82× the forward run, in the per-step writes and reads of them.
    @functools.partial(
        jax.checkpoint,
        prevent_cse=False,
        policy=jax.checkpoint_policies.save_only_these_names(ROOT_NAME),
    )
    def one_step(carry, data):
        g, m, result, failed_step, k, cache = carry
        force = None if forcing is None else forcing.at_step(data, args)
        g_next, m_next, info, cache_next = integrator.cached_step(
            system, g, m, h, cache, force, t0 + k * h
        )
        step_result = checked_step_result(integrator, system, m, h, g_next, m_next, info.result)
        result, failed_step, ok = RESULTS.record(result, failed_step, k, step_result)
        # Saved for the backward pass: all it needs of the step's checks.
        ok = checkpoint_name(ok, ROOT_NAME)
        # After a failure the last good state is carried on (`RESULTS.record`); the saved
        # state is NaN.
        g_next = jnp.where(ok, g_next, g)
        m_next = jnp.where(ok, m_next, m)
        cache_next = jax.tree.map(lambda new, old: jnp.where(ok, new, old), cache_next, cache)
        k = progress.report(k + 1, n_steps)
        carry = (g_next, m_next, result, failed_step, k, cache_next)
        return carry, (info.iterations, info.residual)

    return one_step


def _saved(system, carry):
    """`(carry, g, m)` at a save: the state as saved (NaN after a failure) and the carry
    (in low precision put back on the group, as the saved state is)."""
    g, m, result = carry[0], carry[1], carry[2]
    if drifts_off_group(g.dtype):
        # Low precision: the saved state, from which a run may be continued, is kept
        # on the group (to `membership_tolerance`), as is the state carried on.
        g = system.group.project(g)
        carry = (g, *carry[1:])
    # No silent numbers past the failed step.
    nan = jnp.asarray(jnp.nan, m.dtype)
    ok = result == RESULTS.successful
    return carry, jnp.where(ok, g, nan), jnp.where(ok, m, nan)


def _assemble(system, g0, m0, h, t0, n_steps, save_every, final, saves) -> Solution:
    """The `Solution` from the final carry and the per-save outputs `(g, m, most
    iterations, total iterations, largest residual)` of both loops."""
    gs, ms, iterations, total, residuals = saves
    result, failed_step = final[2], final[3]
    n_saves = n_steps // save_every
    ts = t0 + h * save_every * jnp.arange(n_saves + 1, dtype=m0.dtype)
    stats = {
        "newton_iterations": iterations,
        "residual": residuals,
        "failed_step": failed_step,
        "total_newton_iterations": jnp.sum(total),
        "num_steps": jnp.asarray(n_steps),
    }
    gs = jnp.concatenate([g0[None], gs])
    return Solution(
        ts=ts,
        g=gs,
        m=jnp.concatenate([m0[None], ms]),
        result=result,
        stats=stats,
        advected=advected_of(system, gs),
    )


@eqx.filter_jit
def simulate_scan(
    system,
    integrator,
    g0,
    m0,
    h,
    t0,
    n_steps: int,
    save_every: int,
    segment: int | None = None,
    valid=True,
    progress: AbstractProgressMeter = NoProgressMeter(),
    forcing=None,
    args=None,
) -> Solution:
    """The run as one static scan over saves (`segment`: checkpointed segments)."""
    progress.report(jnp.asarray(0, jnp.int32), n_steps)
    # Per-run state (e.g. a preprocessed method's modified moments for this `h`), once.
    integrator = integrator.init(system, m0, h)
    one_step = _stepper(system, integrator, h, t0, n_steps, progress, forcing, args)

    inner = segment if segment is not None and segment < save_every else None
    outer = segment // save_every if segment is not None and segment > save_every else None

    def one_save(carry, data):
        carry, (iterations, residuals) = scan_in_segments(one_step, carry, save_every, inner, data)
        carry, g, m = _saved(system, carry)
        return carry, (g, m, jnp.max(iterations), jnp.sum(iterations), jnp.max(residuals))

    cache = integrator.step_cache(system, g0)
    init = (g0, m0, *RESULTS.initial(valid), jnp.asarray(0, jnp.int32), cache)
    n_saves = n_steps // save_every
    # Per-step forcing data (a control sequence), scanned over, not indexed: reverse mode
    # then accumulates one row of the cotangent per step.
    per_step = None if forcing is None else forcing.per_step()
    per_step = jax.tree.map(
        lambda x: jnp.asarray(x, m0.dtype).reshape((n_saves, save_every) + jnp.shape(x)[1:]),
        per_step,
    )
    final, saves = scan_in_segments(one_save, init, n_saves, outer, per_step)
    return _assemble(system, g0, m0, h, t0, n_steps, save_every, final, saves)


def simulate_blocks(
    system, integrator, g0, m0, h, t0, n_steps, save_every, valid, progress, axes=None
):
    """The eager run: blocks of saves by one compiled program (`_block`) whatever the
    horizon; the same steps, checks and saves as `simulate_scan`. `axes`: `None` for one
    body, or `(system_axis, h_axis)` (`jax.vmap`'s `in_axes`) for a batch along the leading
    axis of `g0`, `m0` and `valid` (`simulate_batch`'s generic path)."""
    batch = () if axes is None else g0.shape[:1]
    result, failed_step = (jnp.broadcast_to(x, batch) for x in RESULTS.initial(valid))
    # The bodies one step advances, and those of one system (`_compile`).
    stepped = (bodies_of(g0), bodies_per_system(system))
    # A function of `g0` alone (not of `init`'s per-run state): computed once here.
    cache = _initial_cache(system, integrator, g0, axes)
    carry = (g0, m0, result, failed_step, jnp.zeros(batch, jnp.int32), cache)
    # One save's bytes: `g` and `m` of every body (a system of several has one per body),
    # and per system the iteration statistics.
    systems = g0.shape[0] if batch else 1
    size = block_saves((g0.size + m0.size + 2 * systems) * m0.dtype.itemsize + 8 * systems)
    steps, every = as_count(n_steps), as_count(save_every)

    program = _block.for_bodies(*stepped)

    def block(carry, count):
        args = (system, integrator, m0, carry, h, t0, steps, every, count, progress, size, axes)
        return program(*args)

    final, outputs = run_blocks(block, carry, n_steps // save_every, size)
    return _join(system, g0, m0, h, t0, n_steps, save_every, final, outputs, axes)


@once_per_call
def _initial_cache(system, integrator, g0, axes):
    """`AbstractIntegrator.step_cache` at `g0` (per body for a batch), compiled: on the
    blocks' eager path it would otherwise run operation by operation."""
    return _per_body(integrator.step_cache, axes, "system", 0)(system, g0)


def _per_body(fn, axes, *in_axes):
    """`fn` for one body, or vmapped over a batch (`in_axes`: `"system"`, `"h"` or an axis)."""
    if axes is None:
        return fn
    names = {"system": axes[0], "h": axes[1]}
    return jax.vmap(fn, in_axes=tuple(names.get(a, a) for a in in_axes))


@RunProgram
def _block(system, integrator, m0, carry, h, t0, n_steps, save_every, count, progress, size, axes):
    """`count` saves of `save_every` steps each (traced), into buffers of `size` saves."""

    def run(system, m0, carry, h):
        # Per-run state (e.g. a preprocessed method's modified moments for this `h`), from
        # the run's initial momentum `m0`: the same in every block.
        integrator_ = integrator.init(system, m0, h)
        # 0 at the start of a run (a repeat at a later block is not shown again), before
        # the loop: the loop starts from the step count it returns.
        carry = (*carry[:4], progress.report(carry[4], n_steps), carry[5])
        one_step = _stepper(system, integrator_, h, t0, n_steps, progress, None, None)
        _, (iterations, residual) = jax.eval_shape(one_step, carry, None)
        stats0 = (
            jnp.zeros((), iterations.dtype),
            jnp.zeros((), iterations.dtype),
            jnp.full((), -jnp.inf, residual.dtype),
        )

        def step(_, state):
            carry, (most, total, worst) = state
            carry, (iterations, residual) = one_step(carry, None)
            stats = (
                jnp.maximum(most, iterations),
                total + iterations,
                jnp.maximum(worst, residual),
            )
            return carry, stats

        def one_save(index, state):
            carry, buffers = state
            carry, stats = jax.lax.fori_loop(0, save_every, step, (carry, stats0))
            carry, g, m = _saved(system, carry)
            return carry, store(buffers, index, (g, m, *stats))

        shapes = jax.tree.map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), (carry[0], carry[1], *stats0)
        )
        return jax.lax.fori_loop(0, count, one_save, (carry, save_buffers(shapes, size)))

    return _per_body(run, axes, "system", 0, 0, "h")(system, m0, carry, h)


@once_per_call
def _join(system, g0, m0, h, t0, n_steps: int, save_every: int, final, outputs, axes):
    def join(system, g0, m0, h, final, outputs):
        saves = join_blocks(outputs, n_steps // save_every)
        return _assemble(system, g0, m0, h, t0, n_steps, save_every, final, saves)

    return _per_body(join, axes, "system", 0, 0, "h", 0, 0)(system, g0, m0, h, final, outputs)
