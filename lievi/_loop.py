"""The one step loop: every run — one body, a batch, a forced run, a segment of a streamed
or neighbour-list run — steps here (the picture: docs/concepts/simulate.md).

`start` checks the inputs per body, traced (a bad body starts as `RESULTS.invalid_input`),
and builds the stepper's state; each save runs `save_every` steps of `one_step` (the
stepper's step, the failure record of `RESULTS.record`, the statistics reduced in the
carry, the progress meter), then settles and stores the state; `finish` assembles the
`Solution` (the initial save, the saves batch-major, their times). Two drivers run the
same step and save: under a transformation or with per-step forcing data, one static
`lax.scan` over the saves in checkpointed segments; called eagerly, two compiled programs
whatever the horizon (`start`, and a block of saves whose trip counts are traced), each
block's saves copied into the trajectory on the host.
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

from ._checks import is_concrete, raise_if_violated, tracing
from ._newton import ROOT_NAME
from ._results import RESULTS
from ._solution import Solution

# Saves per eager block: long enough that the host loop over blocks (~0.1 ms a dispatch)
# is negligible, short enough to be cheap when few saves are used; a block's buffers
# (filled whole, used or not) are also kept under `BLOCK_BYTES`.
MAX_BLOCK_SAVES = 256
BLOCK_BYTES = 1 << 22


class Run(eqx.Module):
    """What a run is, apart from its inputs: how it steps (`plan`), what it saves, its
    checkpointing and its progress meter."""

    plan: eqx.Module
    save: eqx.Module
    progress: eqx.Module
    dtype: Any = eqx.field(static=True)
    segment: int | None = eqx.field(static=True, default=None)
    unroll: int = eqx.field(static=True, default=1)
    monitor: Any = None  # an invariant monitor (`lievi.EnergyMonitor`), checked at saves
    # The system's parameters checked on the host already (`execute`), not in `start`.
    parameters_checked: bool = eqx.field(static=True, default=False)

    @classmethod
    def of(cls, plan, opts, dtype) -> Run:
        """The run of `plan` with the checked options `opts`. The saves' interval is left
        out (`execute` takes it): as a static field a new `save.every` would recompile."""
        save = dataclasses.replace(opts.save, every=1)
        return cls(plan, save, opts.progress, dtype, opts.segment, opts.tuning.unroll, opts.monitor)


def _zero_counters(batch, dtype, xp=jnp):
    """The statistics' counters of a save interval, `(total, most, worst)` per body."""
    int32 = xp.zeros((batch,), np.int32)
    return int32, int32, xp.full((batch,), -np.inf, dtype)


def _one_step(stepper, progress, n_steps):
    """The loop's step, `(carry, data) → (carry, None)`, `carry = (state, result,
    failed_step, k, counters, reference)`."""

    # Reverse mode keeps each step's input state, the roots of its implicit solves (tagged
    # `ROOT_NAME`) and its survival mask, and recomputes the rest of the step: storing every
    # intermediate made gradients many times the cost of the forward run.
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
        ok = checkpoint_name(ok, ROOT_NAME)  # all the backward pass needs of the checks
        # A failed body carries its last good (finite) state on, so a masked failure cannot
        # make a gradient NaN; what is saved of it is NaN.
        new = stepper.kept(ok, new, state)
        iterations = jnp.where(alive, iterations, 0).astype(jnp.int32)
        residual = jnp.where(alive, residual, -jnp.inf).astype(worst.dtype)
        counters = (total + iterations, jnp.maximum(most, iterations), jnp.fmax(worst, residual))
        k = progress.report(k + 1, n_steps)
        return (new, result, failed_step, k, counters, reference), None

    return one_step


def _save(run, stepper, carry):
    """`(carry, out)` at a save: the state settled, the monitor's check, what is stored
    (batch-major, NaN after a body's failure) and the save's statistics. The run's total of
    Newton iterations stays in the carry; the saves' times are the host's (`finish`)."""
    state, result, failed_step, k, (total, most, worst), reference = carry
    state = stepper.settle(state)
    if run.monitor is not None:
        drifted = jax.vmap(run.monitor.drifted)(reference, _invariants(run, stepper, state))
        failing = drifted & (result == RESULTS.successful)
        result = jnp.where(failing, RESULTS.invariant_drift, result).astype(result.dtype)
        failed_step = jnp.where(failing, k - 1, failed_step)
    ok = result == RESULTS.successful
    out = stepper.stored(state, run.save, ok)
    if run.save.stats:
        out["newton_iterations"], out["residual"] = most, worst
    _, most, worst = _zero_counters(ok.shape[0], worst.dtype)
    return (state, result, failed_step, k, (total, most, worst), reference), out


def _invariants(run, stepper, state):
    return run.plan.invariants(run.monitor, *stepper.configuration(state))


def start(run: Run, g0, m0, h, t0):
    """`(stepper, state, valid, reference, advected)`: the stepper and its initial state,
    the traced input checks (`valid` `(B,)`), the monitor's invariants at the start (`None`
    without a monitor) and the advected parameter at `g0` where it is saved (`None`
    otherwise). The rest of the loop's carry is `_carry`'s."""
    # Before the cast: `g0` to its own dtype's tolerance.
    valid = run.plan.valid(g0, m0, h, t0, parameters=not run.parameters_checked)
    g0, m0, h, t0 = (jnp.asarray(x, run.dtype) for x in (g0, m0, h, t0))
    stepper = run.plan.stepper(g0, m0, h, t0)
    state = stepper.init(g0, m0)
    reference = None if run.monitor is None else _invariants(run, stepper, state)
    advected = stepper.advected_at(g0) if run.save.with_advected() else None
    return stepper, state, valid, reference, advected


def _carry(run: Run, state, valid, reference, xp):
    """The loop's carry before the first step, `(state, result, failed_step, k, counters,
    reference)`, built where the run is (`xp`: NumPy for an eager run, whose `start`
    program then outputs `valid` alone: as its outputs, the results, the step counter and
    the counters were a kernel each)."""
    result, failed_step = RESULTS.initial(valid, xp)
    counters = _zero_counters(valid.shape[0], run.dtype, xp)
    return (state, result, failed_step, xp.asarray(0, np.int32), counters, reference)


def _initial(run: Run, g0, m0, advected, xp):
    """The initial save, `(B, 1, …)`: the inputs themselves, in the run's dtype, built where
    they are (`xp`: NumPy for an eager run: as outputs of `start` each was a copy, a kernel
    of its own)."""
    out = {"g": g0, "m": m0, "advected": advected}
    wanted = {"g": run.save.g, "m": run.save.m, "advected": advected is not None}
    return {k: xp.asarray(v, run.dtype)[:, None] for k, v in out.items() if wanted[k]}


def _saving(run, stepper, n_steps):
    """`one_save(carry, step_loop)`: a save after `step_loop(one_step, carry)` has run its
    steps, what both drivers share."""
    one_step = _one_step(stepper, run.progress, n_steps)

    def one_save(carry, step_loop):
        return _save(run, stepper, step_loop(one_step, carry))

    return one_save


def run_static(run: Run, g0, m0, h, t0, n_steps: int, save_every: int):
    """The run as one static scan over the saves (under a transformation, or with per-step
    forcing data): `(carry, trajectory)`, `trajectory` what is saved, batch-major: `g`, `m`
    and `advected` `(B, 1 + T, …)` from the initial state on, the statistics `(B, T)`."""
    stepper, state, valid, reference, advected = start(run, g0, m0, h, t0)
    carry = _carry(run, state, valid, reference, jnp)
    initial = _initial(run, g0, m0, advected, jnp)
    one_save = _saving(run, stepper, n_steps)
    segment = run.segment
    # Checkpointed segments inside one save interval, or spanning whole save intervals.
    inner = segment if segment is not None and segment < save_every else None
    outer = segment // save_every if segment is not None and segment > save_every else None
    n_saves = n_steps // save_every

    def steps(one_step, carry, data):
        return scan_in_segments(one_step, carry, save_every, inner, data, run.unroll)[0]

    # Per-step data (a control sequence) scanned over, not indexed: reverse mode then
    # accumulates one row of its cotangent per step.
    data = jax.tree.map(
        lambda x: jnp.asarray(x, run.dtype).reshape((n_saves, save_every) + x.shape[1:]),
        run.plan.per_step(),
    )
    # The meter's 0 before the loop: the loop's step counter is the report's result, so
    # the callback is ordered before the loop's (discarded, nothing orders it, and a loaded
    # machine showed the 0 after later updates).
    carry = (*carry[:3], run.progress.report(carry[3], n_steps), *carry[4:])

    def body(carry, data):
        return one_save(carry, lambda one_step, c: steps(one_step, c, data))

    carry, saves = scan_in_segments(body, carry, n_saves, outer, data)
    # The initial save before the saves, batch-major.
    trajectory = {name: jnp.swapaxes(x, 0, 1) for name, x in saves.items()}
    for name, x in initial.items():
        trajectory[name] = jnp.concatenate([x, trajectory[name]], axis=1)
    return carry, trajectory


def scan_in_segments(body, carry, length: int, segment: int | None, xs=None, unroll: int = 1):
    """`lax.scan(body, carry, xs, length)` in `jax.checkpoint`-ed chunks of `segment` steps:
    reverse mode stores the carry at chunk boundaries only, memory `O(length/segment +
    segment)`. (`prevent_cse=False`: a chunk is itself a scan's body, where the guard only
    costs.)"""
    if segment is None or segment >= length:
        return jax.lax.scan(body, carry, xs, length=length, unroll=min(unroll, length))

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def chunk(carry, xs):
        return jax.lax.scan(body, carry, xs, length=segment, unroll=min(unroll, segment))

    xs = jax.tree.map(lambda x: x.reshape((length // segment, segment) + x.shape[1:]), xs)
    carry, ys = jax.lax.scan(chunk, carry, xs, length=length // segment)
    return carry, jax.tree.map(lambda y: y.reshape((length,) + y.shape[2:]), ys)


_start_program = eqx.filter_jit(start)


@functools.partial(eqx.filter_jit, donate="all-except-first")
def _block_program(fixed, buffers):
    """`count ≤ size` saves of `save_every` steps each (all traced) from `carry`, written
    into `buffers` of `size` saves `(size, B, …)`: one program for every horizon.
    `fixed = (run, stepper, carry, n_steps, save_every, count)`, `stepper` `start`'s, its
    per-run constants computed there (the input checks and set-up are not traced and
    compiled again in this program).

    What needs no device is left to the host: the buffers (given, uninitialised, and
    donated), the saves' times and the batch-major layout. Each was a kernel of its own
    here, and XLA's CPU backend compiles every kernel as a module of its own."""
    run, stepper, carry, n_steps, save_every, count = fixed
    one_save = _saving(run, stepper, n_steps)
    # The meter's 0 at the start of a run (not again at a later block), before the loop.
    carry = (*carry[:3], run.progress.report(carry[3], n_steps), *carry[4:])

    def steps(one_step, carry):
        return jax.lax.fori_loop(0, save_every, lambda _, c: one_step(c, None)[0], carry)

    def body(index, both):
        carry, out = one_save(both[0], steps)
        # `index < count ≤ size`: no bounds check (`.at[index].set` compiled one a buffer).
        put = functools.partial(jax.lax.dynamic_update_index_in_dim, index=index, axis=0)
        return carry, jax.tree.map(lambda b, x: put(b, x), both[1], out)

    return jax.lax.fori_loop(0, count, body, (carry, buffers))


def run_eager(run: Run, g0, m0, h, t0, n_steps: int, save_every: int):
    """The eager run: `start` and blocks of saves, two compiled programs whatever the
    horizon. Returns what `run_static` returns, the trajectory as NumPy arrays filled on
    the host."""
    # NumPy scalars: a Python float would be compiled in as a constant, and `jnp.asarray`
    # is a program of its own.
    h, t0 = (x if eqx.is_array(x) else np.asarray(x) for x in (h, t0))
    stepper, state, valid, reference, advected = _start_program(run, g0, m0, h, t0)
    carry = _carry(run, state, np.asarray(valid), reference, np)
    initial = _initial(run, g0, m0, advected, np)
    # A block's saves from one save's bytes (its outputs and the 3 statistics per body):
    # a function of the shapes only, so that a new horizon reuses the compiled block.
    per_body = sum(np.prod(x.shape[1:]) * x.dtype.itemsize for x in jax.tree.leaves(initial))
    size = BLOCK_BYTES // max(1, int(m0.shape[0] * (per_body + 24)))
    size = max(1, min(MAX_BLOCK_SAVES, size))
    n_saves = n_steps // save_every
    steps, every = (np.asarray(x, np.int32) for x in (n_steps, save_every))
    # A save's shapes from the save alone (no step traced), the stepper abstract: concrete,
    # the eager checks of what a save builds (a potential) would compile programs.
    shapes = eqx.filter_eval_shape(
        lambda stepper, c: _saving(run, stepper, steps)(c, lambda f, c: c)[1], stepper, carry
    )
    # The trajectory in its final layout from the start, each block copied into place once
    # (joining the blocks, then the initial save, then handing the result to JAX were three
    # copies of it: 0.3–0.4 of the run's time when a batch of 4096 saved every step).
    # Where the saves start: after the initial save for what has one, at 0 for statistics.
    offset = {name: int(name in initial) for name in shapes}
    trajectory = {
        name: _host_empty((m0.shape[0], offset[name] + n_saves) + s.shape[1:], s.dtype)
        for name, s in shapes.items()
    }
    for name, x in initial.items():
        trajectory[name][:, :1] = x
    # A block's buffers are the last block's, donated back once copied out (no view of
    # them is left, or the donation would be a copy).
    buffers = jax.tree.map(lambda s: np.empty((size,) + s.shape, s.dtype), shapes)
    for begin in range(0, n_saves, size):
        count = min(size, n_saves - begin)
        fixed = (run, stepper, carry, steps, every, np.asarray(count, np.int32))
        carry, buffers = _block_program(fixed, buffers)
        for name, x in buffers.items():
            at = offset[name] + begin
            np.copyto(
                trajectory[name][:, at : at + count], np.swapaxes(np.asarray(x)[:count], 0, 1)
            )
    return carry, trajectory


def _host_empty(shape, dtype):
    """An uninitialised NumPy array on a 64-byte boundary, which `jax.device_put(...,
    may_alias=True)` takes without a copy on the CPU (a misaligned one it copies)."""
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    raw = np.empty(size + 64, np.uint8)
    skip = -raw.ctypes.data % 64
    return raw[skip : skip + size].view(dtype).reshape(shape)


def finish(run: Run, carry, trajectory, times, n_steps: int, save_every: int, xp=jnp):
    """The batch's `Solution` from the saves, batch-major (`run_static`'s `trajectory`;
    `xp`: `jax.numpy` traced, `numpy` for an eager run), with the saves' times
    `t0 + h·save_every·j` (`times`: `(h, t0)`, `h` a scalar or per body)."""
    result, failed_step = carry[1], carry[2]
    stats = {
        "failed_step": failed_step,
        # JAX's default integer, as the sum over the saves it was (`int64` under x64).
        "total_newton_iterations": carry[4][0].astype(jax.dtypes.canonicalize_dtype(int)),
        "num_steps": xp.full(result.shape, n_steps),
    }
    if run.save.stats:
        stats.update(
            newton_iterations=trajectory["newton_iterations"], residual=trajectory["residual"]
        )
    g, m, advected = (trajectory.get(name) for name in ("g", "m", "advected"))
    h, t0 = (xp.asarray(x, run.dtype) for x in times)
    j = xp.arange(n_steps // save_every + 1, dtype=run.dtype)
    t = xp.broadcast_to(t0 + h[..., None] * save_every * j, (result.shape[0], j.shape[0]))
    return Solution(t, g, m, result, stats, advected=advected)


def execute(
    run: Run,
    g0,
    m0,
    h,
    t0,
    n_steps: int,
    save_every: int,
    *,
    explain,
    one: bool = False,
    throw: tuple[str, str] | None = None,
) -> Solution:
    """The run of a batch, eagerly (`run_eager`) or traced (`run_static`), and its
    `Solution` (`one`: of the batch's one body, without the batch axis). `explain(i)`
    raises the `ValueError` that names body `i`'s bad input, for an eager run whose body
    `i` is the first found invalid (`RESULTS.invalid_input`). `throw`:
    `raise_if_failed`'s `(label, what)`, or `None` to return failures in `result`. The
    traced check is part of the run's program: applied to its outputs after the program,
    under a transformation without an outer `jit` (e.g. `jax.grad` of an eager call), each
    of its operations was a program of its own (14 for a gradient)."""
    eager = (
        not tracing()
        and is_concrete(*jax.tree.leaves((run, g0, m0, h, t0)))
        and run.plan.per_step() is None
        and run.unroll == 1
        # A batch placed over several devices (`lievi.shard_batch`) runs as one program
        # that keeps its sharding; the eager blocks join their outputs on one host.
        and not any(isinstance(x, jax.Array) and len(x.sharding.device_set) > 1 for x in (g0, m0))
    )
    if not eager:
        return _static_program(run, g0, m0, h, t0, n_steps, save_every, one=one, throw=throw)
    if run.plan.system_axis is None:
        # One system for every body: its parameters checked once, on the host, by the
        # program its constructor compiled (`raise_if_violated`), not per body in `start`
        # (a test of positive definiteness is a loop there: 5 of its 33 kernels, SO(3)).
        raise_if_violated(run.plan.system.parameter_conditions)
        run = dataclasses.replace(run, parameters_checked=True)
    carry, trajectory = run_eager(run, g0, m0, h, t0, n_steps, save_every)
    invalid = np.flatnonzero(np.asarray(carry[1]) == int(RESULTS.invalid_input))
    if invalid.size:
        explain(int(invalid[0]))
    carry = jax.tree.map(np.asarray, carry)
    solution = finish(run, carry, trajectory, (h, t0), n_steps, save_every, xp=np)
    if throw is not None:  # on the host: the results are concrete
        raise_if_failed(solution, *throw)
    # On the device by a transfer, no program (`jnp.asarray` would compile one per shape),
    # and on the CPU no copy of the trajectory either: it was filled for JAX to take
    # (`_host_empty`), and nothing else holds it.
    return jax.device_put(_first(solution) if one else solution, may_alias=True)


@eqx.filter_jit
def _static_program(run, g0, m0, h, t0, n_steps: int, save_every: int, *, one, throw):
    carry, trajectory = run_static(run, g0, m0, h, t0, n_steps, save_every)
    solution = finish(run, carry, trajectory, (h, t0), n_steps, save_every)
    solution = _first(solution) if one else solution
    return solution if throw is None else raise_if_failed(solution, *throw)


def _first(solution: Solution) -> Solution:
    return jax.tree.map(lambda x: x[0], solution)


def raise_if_failed(solution: Solution, label: str, what: str) -> Solution:
    """`solution`, or an error if a body failed (`throw=True`): raised now for a concrete
    result, else a runtime check riding on every output (a check on an unused output under
    the caller's `jit` would be dropped silently). It is made on a scalar whose zero is
    added to every output, so the outputs do not pass through the error's callback (whose
    replicated layout would gather a sharded batch onto every device)."""
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
