"""The one step loop: every run — one body, a batch, a forced run, a segment of a streamed
or neighbour-list run — steps here.

What runs, in order (a batch of `B` bodies; one body is a batch of one):

1. `start`: the input checks, per body, traced (`AbstractPlan.valid`: a bad body starts as
   `RESULTS.invalid_input`), the stepper's initial state and the initial save;
2. the saves: per save, `save_every` steps of `one_step` — the stepper's step, the
   failure record (`RESULTS.record`: the first failure and its step are kept, a failed
   body's state is held at its last good value and saved as NaN), the Newton statistics
   reduced in the carry, the progress meter — then the state settled and stored;
3. `finish`: the per-save outputs batch-major, the initial save in front, the `Solution`.

Two drivers run the same `one_step` and the same save:

- under a transformation (`jax.jit`, `jax.grad`, `jax.vmap` of the caller) or with per-step
  forcing data, one static `lax.scan` over the saves, in `jax.checkpoint`-ed segments
  (`lievi._scan`): the program of the caller;
- called eagerly, two compiled programs whatever the horizon: `start`, and a block of
  saves whose trip counts (`save_every`, the saves in the block, `n_steps` for the meter)
  and `h`, `t0` are traced values, called once per block of saves. A new `n_steps`, `h`,
  `t0`, `g0`, `m0` or new parameter values of the system reuse both; the blocks' outputs
  are joined on the host.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from ._checks import is_concrete, tracing
from ._newton import ROOT_NAME
from ._results import RESULTS
from ._scan import scan_in_segments
from ._solution import Solution
from ._steppers import where_ok

# Saves per eager block: a block's output buffers are this many saves long whatever the
# horizon, so a block must be short enough to be cheap when few saves are used and long
# enough that the host loop over blocks (one dispatch each, ~0.1 ms) is negligible.
MAX_BLOCK_SAVES = 256
# A block's output buffers are kept under this many bytes: they are filled whole, used or
# not, so a large block costs run time on a short run of a large batch.
BLOCK_BYTES = 1 << 22


class Run(eqx.Module):
    """What a run is, apart from its inputs: how it steps (`plan`), what it saves, its
    checkpointing and its progress meter. `n_steps` and `save_every` are Python ints for
    the static driver; the eager driver passes them as traced counts instead."""

    plan: eqx.Module
    save: eqx.Module
    progress: eqx.Module
    dtype: Any = eqx.field(static=True)
    segment: int | None = eqx.field(static=True, default=None)
    unroll: int = eqx.field(static=True, default=1)
    monitor: Any = None  # an invariant monitor (`lievi.EnergyMonitor`), checked at saves

    @classmethod
    def of(cls, plan, opts, dtype) -> Run:
        """The run of `plan` with the checked options `opts` (`lievi._options.Options`).
        The saves' interval is left out (`execute` takes it): a static field would make a
        new `save.every` compile the eager run again."""
        save = dataclasses.replace(opts.save, every=1)
        return cls(plan, save, opts.progress, dtype, opts.segment, opts.tuning.unroll, opts.monitor)


def _zero_counters(batch, dtype):
    return (
        jnp.zeros((batch,), jnp.int32),
        jnp.zeros((batch,), jnp.int32),
        jnp.full((batch,), -jnp.inf, dtype),
    )


def _one_step(stepper, progress, n_steps):
    """The step of the loop, `(carry, data) → (carry, None)` with `carry = (state, result,
    failed_step, k, counters)`."""

    # Reverse mode keeps each step's input state, the roots of its implicit solves (tagged
    # `ROOT_NAME`) and its survival mask, and recomputes the rest of the step in the
    # backward pass: storing every intermediate of a step made gradients many times the
    # cost of the forward run, in the per-step writes and reads of them.
    @functools.partial(
        jax.checkpoint,
        prevent_cse=False,
        policy=jax.checkpoint_policies.save_only_these_names(ROOT_NAME),
    )
    def one_step(carry, data):
        state, result, failed_step, k, (total, most, worst), reference = carry
        alive = result == RESULTS.successful
        new, code, iterations, residual = stepper.step(state, data, k, alive)
        result, failed_step, ok = RESULTS.record(result, failed_step, k, code)
        # Saved for the backward pass (one byte a body-step): all it needs of the checks.
        ok = checkpoint_name(ok, ROOT_NAME)
        # After a failure the last good state is carried on (finite numbers, so a masked
        # failure cannot make a gradient NaN); the saved state is NaN.
        new = where_ok(ok, new, state)
        # Statistics reduced in the carry, not stacked per step.
        iterations = jnp.where(alive, iterations, 0).astype(jnp.int32)
        residual = jnp.where(alive, residual, -jnp.inf).astype(worst.dtype)
        counters = (total + iterations, jnp.maximum(most, iterations), jnp.fmax(worst, residual))
        k = progress.report(k + 1, n_steps)
        return (new, result, failed_step, k, counters, reference), None

    return one_step


def _save(run, stepper, carry, h, t0, save_every):
    """`(carry, out)` at a save: the state settled, the invariant monitor's check, what is
    stored of the state (NaN after a body's failure), the statistics, and the save's time
    `t0 + h·save_every·j`."""
    save = run.save
    state, result, failed_step, k, (total, most, worst), reference = carry
    state = stepper.settle(state)
    if run.monitor is not None:
        drifted = jax.vmap(run.monitor.drifted)(reference, _invariants(run, stepper, state))
        failing = drifted & (result == RESULTS.successful)
        result = jnp.where(failing, RESULTS.invariant_drift, result).astype(result.dtype)
        failed_step = jnp.where(failing, k - 1, failed_step)
    ok = result == RESULTS.successful
    out = stepper.stored(state, save, ok)
    out["iterations"] = total
    if save.stats:
        out["newton_iterations"] = most
        out["residual"] = worst
    j = (k // save_every).astype(worst.dtype)
    out["t"] = jnp.broadcast_to(t0 + h * save_every * j, ok.shape)
    counters = _zero_counters(ok.shape[0], worst.dtype)
    return (state, result, failed_step, k, counters, reference), out


def _invariants(run, stepper, state):
    """The monitor's invariant of every body of `state`, `(B, k)`."""
    return run.plan.invariants(run.monitor, *stepper.configuration(state))


def _layout(stepper, stacked):
    """Stacked saves `(T, …)` batch-major; `iterations` summed over the saves."""
    out = stepper.layout({k: v for k, v in stacked.items() if k in ("g", "m", "advected")})
    out["iterations"] = jnp.sum(stacked["iterations"], axis=0)
    for name in ("newton_iterations", "residual", "t"):
        if name in stacked:
            out[name] = stacked[name].T
    return out


def start(run: Run, g0, m0, h, t0):
    """`(stepper, carry, initial)`: the traced input checks, the stepper and its initial
    state, and the initial save (batch-major)."""
    plan = run.plan
    # Before the cast: `g0` is held to the membership tolerance of its own dtype.
    valid = plan.valid(g0, m0, h, t0)
    dtype = run.dtype
    g0, m0, h, t0 = (jnp.asarray(x, dtype) for x in (g0, m0, h, t0))
    stepper = plan.stepper(g0, m0, h, t0)
    batch = m0.shape[0]
    result, failed_step = (jnp.broadcast_to(x, (batch,)) for x in RESULTS.initial(valid))
    state = stepper.init(g0, m0)
    reference = None if run.monitor is None else _invariants(run, stepper, state)
    carry = (state, result, failed_step, jnp.asarray(0, jnp.int32))
    initial = stepper.initial(g0, m0, run.save)
    initial["t"] = jnp.broadcast_to(t0, (batch,))[:, None]
    return stepper, (*carry, _zero_counters(batch, dtype), reference), initial


def run_static(run: Run, g0, m0, h, t0, n_steps: int, save_every: int):
    """The run as one static scan over the saves (under a transformation, or with per-step
    forcing data): `(carry, initial, saves)`, the saves batch-major."""
    stepper, carry, initial = start(run, g0, m0, h, t0)
    dtype = run.dtype
    h, t0 = jnp.asarray(h, dtype), jnp.asarray(t0, dtype)
    one_step = _one_step(stepper, run.progress, n_steps)
    segment = run.segment
    # Checkpointed segments inside one save interval, or spanning whole save intervals.
    inner = segment if segment is not None and segment < save_every else None
    outer = segment // save_every if segment is not None and segment > save_every else None
    n_saves = n_steps // save_every

    def one_save(carry, data):
        carry, _ = scan_in_segments(one_step, carry, save_every, inner, data, run.unroll)
        return _save(run, stepper, carry, h, t0, save_every)

    data = run.plan.per_step()
    # Per-step data (a control sequence) scanned over, not indexed: reverse mode then
    # accumulates one row of its cotangent per step.
    data = jax.tree.map(
        lambda x: jnp.asarray(x, dtype).reshape((n_saves, save_every) + x.shape[1:]), data
    )
    run.progress.report(jnp.asarray(0, jnp.int32), n_steps)
    carry, saves = scan_in_segments(one_save, carry, n_saves, outer, data)
    return carry, initial, _layout(stepper, saves)


def block_saves(bytes_per_save: int) -> int:
    """Saves per eager block for saves of `bytes_per_save` bytes (a function of the shapes
    only, never of the horizon, so that a new horizon reuses the compiled block)."""
    return max(1, min(MAX_BLOCK_SAVES, BLOCK_BYTES // max(1, bytes_per_save)))


@eqx.filter_jit
def _start_program(run, g0, m0, h, t0):
    _, carry, initial = start(run, g0, m0, h, t0)
    return carry, initial


@eqx.filter_jit
def _block_program(run, inputs, carry, n_steps, save_every, count, size: int):
    """`count ≤ size` saves of `save_every` steps each (all traced), into buffers of
    `size` saves: one program for every horizon. `inputs`: the run's `(g0, m0, h, t0)`."""
    g0, m0, h, t0 = inputs
    stepper, _, _ = start(run, g0, m0, h, t0)
    dtype = run.dtype
    h, t0 = jnp.asarray(h, dtype), jnp.asarray(t0, dtype)
    one_step = _one_step(stepper, run.progress, n_steps)
    # 0 at the start of a run (a repeat at a later block is not shown again), before the
    # loop: the loop starts from the step count it returns.
    carry = (*carry[:3], run.progress.report(carry[3], n_steps), *carry[4:])

    def one_save(carry):
        carry = jax.lax.fori_loop(0, save_every, lambda _, c: one_step(c, None)[0], carry)
        return _save(run, stepper, carry, h, t0, save_every)

    # A save's shapes from the save alone (tracing `one_save` would trace the step again).
    shapes = jax.eval_shape(lambda c: _save(run, stepper, c, h, t0, save_every)[1], carry)
    buffers = jax.tree.map(lambda s: jnp.zeros((size,) + s.shape, s.dtype), shapes)

    def body(index, both):
        carry, buffers = both
        carry, out = one_save(carry)
        return carry, jax.tree.map(lambda b, x: b.at[index].set(x), buffers, out)

    carry, buffers = jax.lax.fori_loop(0, count, body, (carry, buffers))
    # Batch-major here, once: the host only concatenates.
    return carry, _layout(stepper, buffers)


def run_eager(run: Run, g0, m0, h, t0, n_steps: int, save_every: int):
    """The eager run: `start` and blocks of saves, two compiled programs whatever the
    horizon. Returns what `run_static` returns, as NumPy arrays joined on the host."""
    # NumPy scalars, not Python floats (which `eqx.filter_jit` would compile in as
    # constants) nor `jnp.asarray` (a program of its own, compiled at the first call).
    h, t0 = (x if eqx.is_array(x) else np.asarray(x) for x in (h, t0))
    carry, initial = _start_program(run, g0, m0, h, t0)
    batch = m0.shape[0]
    # One save's bytes: its outputs for every body, and the statistics.
    per_body = sum(np.prod(x.shape[1:]) * x.dtype.itemsize for x in jax.tree.leaves(initial))
    size = block_saves(int(batch * (per_body + 3 * 8)))
    n_saves = n_steps // save_every
    steps, every = (np.asarray(x, np.int32) for x in (n_steps, save_every))
    outputs = []
    for begin in range(0, n_saves, size):
        count = np.asarray(min(size, n_saves - begin), np.int32)
        carry, out = _block_program(run, (g0, m0, h, t0), carry, steps, every, count, size)
        outputs.append(out)
    saves = {
        name: sum(np.asarray(x[name]) for x in outputs)
        if name == "iterations"
        else np.concatenate([np.asarray(x[name]) for x in outputs], axis=1)[:, :n_saves]
        for name in outputs[0]
    }
    return carry, initial, saves


def finish(carry, initial, saves, n_steps: int, save: eqx.Module, xp=jnp) -> Solution:
    """The batch's `Solution` (`xp`: `jax.numpy` for a traced run, `numpy` for an eager
    one, joined on the host)."""
    _, result, failed_step, _, _, _ = carry
    batch = result.shape[0]
    stats = {
        "failed_step": failed_step,
        "total_newton_iterations": saves["iterations"],
        "num_steps": xp.full((batch,), n_steps),
    }
    if save.stats:
        stats["newton_iterations"] = saves["newton_iterations"]
        stats["residual"] = saves["residual"]
    fields = {
        name: xp.concatenate([xp.asarray(initial[name]), saves[name]], axis=1)
        if name in saves
        else None
        for name in ("g", "m", "advected", "t")
    }
    return Solution(
        ts=fields["t"],
        g=fields["g"],
        m=fields["m"],
        result=result,
        stats=stats,
        advected=fields["advected"],
    )


def execute(
    run: Run, g0, m0, h, t0, n_steps: int, save_every: int, *, explain, one: bool = False
) -> Solution:
    """The run of a batch, eagerly (`run_eager`, the outputs joined on the host) or traced
    (`run_static`), and its `Solution` (`one`: of the batch's one body, without the batch
    axis). `explain()` raises the `ValueError` that names a bad input; an eager run calls
    it when a body starts as `RESULTS.invalid_input`."""
    eager = (
        not tracing()
        and is_concrete(*jax.tree.leaves((run, g0, m0, h, t0)))
        and run.plan.per_step() is None
        and run.unroll == 1
        # A batch placed over several devices (`lievi.shard_batch`) runs as one program
        # that keeps its sharding; the eager blocks join their outputs on one host.
        and not _spans_devices(g0, m0)
    )
    if not eager:
        return _static_program(run, g0, m0, h, t0, n_steps, save_every, one)
    carry, initial, saves = run_eager(run, g0, m0, h, t0, n_steps, save_every)
    if np.any(np.asarray(carry[1]) == int(RESULTS.invalid_input)):
        explain()
    carry = jax.tree.map(np.asarray, carry)
    initial = jax.tree.map(np.asarray, initial)
    solution = finish(carry, initial, saves, n_steps, run.save, xp=np)
    # On the device: a transfer, no program (`jnp.asarray` of a NumPy array would compile
    # one per shape, hence per horizon).
    return jax.device_put(_first(solution) if one else solution)


@eqx.filter_jit
def _static_program(run, g0, m0, h, t0, n_steps: int, save_every: int, one: bool) -> Solution:
    carry, initial, saves = run_static(run, g0, m0, h, t0, n_steps, save_every)
    solution = finish(carry, initial, saves, n_steps, run.save)
    return _first(solution) if one else solution


def _spans_devices(*arrays) -> bool:
    """Whether any of `arrays` is a JAX array placed over more than one device."""
    return any(isinstance(x, jax.Array) and len(x.sharding.device_set) > 1 for x in arrays)


def _first(solution: Solution) -> Solution:
    """The batch of one's leading axis off."""
    return jax.tree.map(lambda x: x[0], solution)


def raise_if_failed(solution: Solution, label: str, what: str) -> Solution:
    """`solution`, or an error if a body failed (`throw=True`): raised now for an eager
    run's concrete result, else a runtime check riding on every output (under the caller's
    `jit` a check on an unused output would be dead code and dropped silently). The check
    is made on a scalar whose zero is added to every output, so the outputs themselves do
    not pass through the error's callback (whose replicated layout would gather a batch
    sharded over devices or processes onto every device)."""
    messages = [
        f"{label}: {what} failed: {message} (Run with throw=False to get the partial "
        "trajectory, `result` and `stats['failed_step']`.)"
        for message in RESULTS.messages
    ]
    result = solution.result
    if is_concrete(result) and not tracing():
        codes = np.asarray(result)
        failed = codes[codes != int(RESULTS.successful)]
        if failed.size:
            raise RuntimeError(messages[int(failed.max())])
        return solution
    failed = result != RESULTS.successful
    first = jnp.max(jnp.where(failed, result, 0))
    zero = eqx.branched_error_if(jnp.zeros((), jnp.int32), jnp.any(failed), first, messages)
    return jax.tree.map(lambda x: x + zero.astype(x.dtype), solution)
