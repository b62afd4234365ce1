"""`simulate_batch`'s fast path: one kernel (`AbstractBatchKernel`) inside one `lax.scan`.

The state is structure of arrays, component-major with the batch minor; the kernel owns
the layout (`carried`, `elements`). The loop adds what every method gets: the step bound
(`turn_squared`), failure masking per body (a failed body's state becomes NaN and costs no
further Newton iterations), statistics reduced in the carry, and checkpointing.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from ._kernels._base import ROOT_NAME
from ._progress import AbstractProgressMeter, NoProgressMeter
from ._results import RESULTS
from ._scan import scan_in_segments
from ._solution import Solution


@eqx.filter_jit
def simulate_kernel(
    kernel,
    constants,
    step_bound,
    g0,
    m0,
    h,
    n_steps,
    save_every,
    save,
    unroll,
    segment,
    valid=True,
    group=None,
    t0=0.0,
    progress: AbstractProgressMeter = NoProgressMeter(),
):
    """`group`: where given, the carried elements are put back on it (`project`) at each
    save, as `simulate` does in low precision (`lievi._checks.drifts_off_group`). `t0`:
    the time of the first saved state. `progress`: the meter told the steps done (nothing
    is compiled for `NoProgressMeter`).

    `simulate` runs one body here too, as a batch of one: under `jax.vmap` each component
    is then one `(B, 1)` array, the layout `simulate_batch` runs in."""
    batch, dtype = g0.shape[0], m0.dtype
    constants = jax.tree.map(lambda x: jnp.asarray(x, dtype), constants)
    # Structure of arrays: component-major, batch minor; the kernel owns the layout.
    constants = kernel.constants(constants, batch)
    params = kernel.prepare(constants, h)
    # The kernel's carried entries of `g` (on SO(3) all 9, or the advected parameter
    # alone on the reduced path).
    g = kernel.carried(g0)
    m = tuple(m0[:, i] for i in range(m0.shape[1]))
    nan = jnp.asarray(jnp.nan, dtype)
    int32 = jnp.int32
    # Per-run constants of the step-size check, once outside the loop: the per-step check
    # then needs no division and no square root (both run at a fraction of the rate of a
    # product on CPU).
    turn_rates = kernel.turn_rates(constants, h)

    def _checked_step_result(g_next, m_next, m, step_result):
        """`lievi._simulate.checked_step_result` on structure of arrays."""
        finite = jnp.isfinite(g_next[0])
        for x in (*g_next[1:], *m_next):
            finite = finite & jnp.isfinite(x)
        # (h|ω|)² > bound², as h|ω| > bound but for rounding at the bound.
        too_large = kernel.turn_squared(turn_rates, m) > step_bound * step_bound
        return RESULTS.checked(step_result, finite, too_large)

    # Reverse mode keeps each step's input state and root (the solve is not repeated);
    # everything else in the step is recomputed from them in the backward pass.
    @functools.partial(
        jax.checkpoint,
        prevent_cse=False,
        policy=jax.checkpoint_policies.save_only_these_names(ROOT_NAME),
    )
    def one_step(carry, _):
        (g, m, result, failed_step, k), (total, most, worst) = carry
        alive = result == RESULTS.successful
        g_next, m_next, step_result, iterations, residual = kernel.step(params, g, m, alive)
        step_result = _checked_step_result(g_next, m_next, m, step_result)
        result, failed_step, ok = RESULTS.record(result, failed_step, k, step_result)
        # Saved for the backward pass (one byte a body-step): the mask is all the backward
        # needs of the step's checks, which would otherwise re-evaluate the whole step
        # (`g_next`, the Newton residual) just to know which bodies survived it.
        ok = checkpoint_name(ok, ROOT_NAME)
        # After a failure the last good state is carried on (`RESULTS.record`; the kernel
        # spends no extra iterations on it); the saved state is NaN.
        g_next = tuple(jnp.where(ok, x, y) for x, y in zip(g_next, g))
        m_next = tuple(jnp.where(ok, x, y) for x, y in zip(m_next, m))
        # Statistics are reduced in the carry, not stacked per step: a (steps, B) output
        # would cost more memory traffic than the state itself.
        iterations = jnp.where(alive, iterations, 0)
        residual = jnp.where(alive, residual, -jnp.inf)
        counters = (total + iterations, jnp.maximum(most, iterations), jnp.fmax(worst, residual))
        progress.report(k + 1, n_steps)
        return ((g_next, m_next, result, failed_step, k + 1), counters), None

    zero_counters = (
        jnp.zeros((batch,), int32),
        jnp.zeros((batch,), int32),
        jnp.full((batch,), -jnp.inf, dtype),
    )
    # Checkpointed segments inside one save interval, or spanning whole save intervals.
    inner = segment if segment is not None and segment < save_every else None
    outer = segment // save_every if segment is not None and segment >= save_every else None

    def one_save(state, _):
        (state, (total, most, worst)), _ = scan_in_segments(
            one_step, (state, zero_counters), save_every, inner, unroll=unroll
        )
        if group is not None:
            # (k, B) entries → (B, n, n) elements → projected → the kernel's entries.
            elements = group.project(kernel.elements(jnp.stack(state[0])[None])[:, 0])
            state = (kernel.carried(elements), *state[1:])
        ok = state[2] == RESULTS.successful
        out = {"iterations": total}
        if save.g:
            out["g"] = jnp.where(ok, jnp.stack(state[0]), nan)
        if save.m:
            out["m"] = jnp.where(ok, jnp.stack(state[1]), nan)
        if save.advected:
            out["advected"] = jnp.where(ok, jnp.stack(kernel.advected(state[0])), nan)
        if save.stats:
            out["max_iterations"] = most
            out["residual"] = worst
        return state, out

    progress.report(jnp.asarray(0, int32), n_steps)
    result0, failed_step0 = (jnp.broadcast_to(x, (batch,)) for x in RESULTS.initial(valid))
    init = (g, m, result0, failed_step0, jnp.asarray(0, int32))
    final, out = scan_in_segments(one_save, init, n_steps // save_every, outer)
    _, _, result, failed_step, _ = final
    n_saves = n_steps // save_every
    # As `simulate`: t0 + h·save_every·k.
    ts = t0 + (h[:, None] if h.ndim else h) * save_every * jnp.arange(n_saves + 1, dtype=dtype)
    ts = jnp.broadcast_to(ts, (batch, n_saves + 1))
    stats = {
        "failed_step": failed_step,
        "total_newton_iterations": jnp.sum(out["iterations"], axis=0),
        "num_steps": jnp.full((batch,), n_steps),
    }
    if save.stats:
        stats["newton_iterations"] = out["max_iterations"].T
        stats["residual"] = out["residual"].T
    gs = ms = None
    if save.g:
        # (T−1, k, B) → (B, T, n, n), initial state first.
        gs = jnp.concatenate([g0[:, None], kernel.elements(out["g"])], axis=1)
    if save.m:
        ms = jnp.concatenate([m0[:, None], jnp.moveaxis(out["m"], -1, 0)], axis=1)
    advected = None
    if save.advected:
        advected0 = jnp.stack(kernel.advected(g), axis=-1)
        advected = jnp.concatenate(
            [advected0[:, None], jnp.moveaxis(out["advected"], -1, 0)], axis=1
        )
    return Solution(ts=ts, g=gs, m=ms, result=result, stats=stats, advected=advected)
