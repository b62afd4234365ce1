"""`simulate_batch`'s fast path: one kernel (`AbstractBatchKernel`) inside one step loop.

The state is structure of arrays, component-major with the batch minor; the kernel owns
the layout (`carried`, `elements`). The loop adds what every method gets: the step bound
(`turn_squared`), failure masking per body (a failed body's state becomes NaN and costs no
further Newton iterations), statistics reduced in the carry, and checkpointing.

The loop is a static `lax.scan` under a transformation, and blocks of saves by one
compiled program whatever the horizon in an eager call (`lievi._horizon`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from ._checks import abstract_key, abstract_tree
from ._compile import RunProgram, bodies_of, once_per_call
from ._horizon import as_count, block_saves, horizon_traced, run_blocks, save_buffers, store
from ._kernels._base import ROOT_NAME
from ._progress import AbstractProgressMeter, NoProgressMeter
from ._results import RESULTS
from ._scan import scan_in_segments
from ._solution import Solution

# Runs of up to this many bodies try the kernel without its Newton loop first
# (`_kernel_blocks`). Leaving the loop out saves about the same compile time at every batch
# size (SE(3) `DEP`: 0.9–1.1 s of 3–4 s from 64 to 4096 bodies on a 2-core CPU,
# `benchmarks/fixed_first.py`), but the chance that some step of some body needs the loop,
# and both programs are compiled, grows with the bodies, while the compile's share of a
# call shrinks (10⁴ SE(3) bodies run 10³ steps in about 1.7 s there).
FIXED_FIRST_MAX_BODIES = 1024


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
    is then one `(B, 1)` array, the layout `simulate_batch` runs in.

    Eagerly (and with `unroll = 1`) the saves run in blocks of one compiled program whatever
    `n_steps` and `save_every` (`lievi._horizon`); under a transformation, one static scan."""
    args = (kernel, constants, step_bound, g0, m0, h)
    if unroll == 1 and horizon_traced(*args, valid, t0):
        return _kernel_blocks(*args, n_steps, save_every, save, valid, group, t0, progress)
    args = (*args, n_steps, save_every, save, unroll, segment, valid, group, t0, progress)
    return _kernel_scan(*args)


def _setup(kernel, constants, step_bound, g0, m0, h, valid, n_steps, progress):
    """`(one_step, init)`: the checked step on the kernel's structure of arrays and the
    initial state (both loops; `n_steps` static or traced, for the meter)."""
    batch, dtype = g0.shape[0], m0.dtype
    constants = jax.tree.map(lambda x: jnp.asarray(x, dtype), constants)
    # Structure of arrays: component-major, batch minor; the kernel owns the layout.
    constants = kernel.constants(constants)
    params = kernel.prepare(constants, h)
    # The kernel's carried entries of `g` (on SO(3) all 9, or the advected parameter
    # alone on the reduced path).
    g = kernel.carried(g0)
    m = tuple(m0[:, i] for i in range(m0.shape[1]))
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
        k = progress.report(k + 1, n_steps)
        return ((g_next, m_next, result, failed_step, k), counters), None

    result0, failed_step0 = (jnp.broadcast_to(x, (batch,)) for x in RESULTS.initial(valid))
    init = (g, m, result0, failed_step0, jnp.asarray(0, jnp.int32))
    return one_step, init


def _zero_counters(batch, dtype):
    int32 = jnp.int32
    return (
        jnp.zeros((batch,), int32),
        jnp.zeros((batch,), int32),
        jnp.full((batch,), -jnp.inf, dtype),
    )


def _outputs(kernel, state, counters, save, group):
    """`(state, out)` at a save: the state (put back on `group` where given) and what is
    stored of it (NaN after a body's failure)."""
    total, most, worst = counters
    if group is not None:
        # (k, B) entries → (B, n, n) elements → projected → the kernel's entries.
        elements = group.project(kernel.elements(jnp.stack(state[0])[None])[:, 0])
        state = (kernel.carried(elements), *state[1:])
    nan = jnp.asarray(jnp.nan, worst.dtype)
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


@eqx.filter_jit
def _kernel_scan(
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
    valid,
    group,
    t0,
    progress,
):
    setup = (kernel, constants, step_bound, g0, m0, h, valid, n_steps, progress)
    one_step, init = _setup(*setup)
    zero_counters = _zero_counters(g0.shape[0], m0.dtype)
    # Checkpointed segments inside one save interval, or spanning whole save intervals.
    inner = segment if segment is not None and segment < save_every else None
    outer = segment // save_every if segment is not None and segment >= save_every else None

    def one_save(state, _):
        (state, counters), _ = scan_in_segments(
            one_step, (state, zero_counters), save_every, inner, unroll=unroll
        )
        return _outputs(kernel, state, counters, save, group)

    progress.report(jnp.asarray(0, jnp.int32), n_steps)
    final, out = scan_in_segments(one_save, init, n_steps // save_every, outer)
    out = _layout(kernel, out)
    return _solution(kernel, g0, m0, h, t0, n_steps, save_every, save, final, out)


def _kernel_blocks(
    kernel, constants, step_bound, g0, m0, h, n_steps, save_every, save, valid, group, t0, progress
):
    """The eager run: blocks of saves by one compiled program (`_block`) whatever the
    horizon; the same steps and saves as `_kernel_scan`.

    A run of up to `FIXED_FIRST_MAX_BODIES` bodies without a progress meter first runs the
    kernel without the Newton loop after its fixed iterations
    (`AbstractBatchKernel.fixed_iterations_only`), which compiles sooner (SE(3) `DEP`:
    about 1 s of 3–4 s on a 2-core CPU) and at the usual step sizes takes the same
    steps; from the first block in which the fixed iterations fail a body, the run is the
    whole kernel's, that block again included (`run_blocks`). A larger batch compiles the
    whole kernel at once: the more bodies, the likelier that some step of one of them
    needs the loop and both programs are compiled, and the less the compile counts beside
    the run. With a meter, a block run again would report its steps twice."""
    args = (kernel, constants, step_bound, g0, m0, h, valid, save, group)
    stepped = bodies_of(g0)  # the bodies one step advances (`_compile`)
    init = _initial(*args)
    shapes = _save_shapes(kernel, init, save, group)
    size = block_saves(sum(s.size * s.dtype.itemsize for s in jax.tree.leaves(shapes)))
    steps, every = as_count(n_steps), as_count(save_every)

    program = _block.for_bodies(stepped)

    def block(state, count, kernel=kernel):
        return program(kernel, *args[1:], progress, state, steps, every, count, shapes, size)

    light, needed_loop = None, None
    if g0.shape[0] <= FIXED_FIRST_MAX_BODIES and not progress.reports:
        # Once a run of this kernel on these shapes has needed the loop, its whole program
        # is compiled, and trying the light one first would only run blocks twice.
        needed_loop = _hashable(abstract_key((kernel, init)))
        if needed_loop is None or needed_loop not in _NEEDED_LOOP:
            light = kernel.fixed_iterations_only()
    first = None if light is None else functools.partial(block, kernel=light)

    def kept(before, after):
        if _no_new_failure(before, after):
            return True
        if needed_loop is not None:
            _NEEDED_LOOP.add(needed_loop)
        return False

    final, outputs = run_blocks(block, init, n_steps // save_every, size, first, kept)
    return _join(kernel, g0, m0, h, t0, n_steps, save_every, save, final, outputs)


# `abstract_key((kernel, initial state))` of the eager runs whose light program failed a body.
_NEEDED_LOOP: set = set()


def _hashable(key):
    """`key`, or `None` where it cannot be hashed (an unhashable kernel or group field):
    such a run is not remembered (`_NEEDED_LOOP`) and its save shapes are not cached."""
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _no_new_failure(before, after) -> bool:
    """Whether no body that was `RESULTS.successful` at a block's start (state `before`)
    failed in it (state `after`): on the host, in NumPy (it waits for the block; as JAX
    operations, eagerly, the test compiled two small programs of its own). A body already
    failed at the block's start stays failed in either kernel (its state is NaN and it is
    not stepped), so it does not by itself make the run the whole kernel's."""
    return not np.any(
        (np.asarray(before[2]) == int(RESULTS.successful))
        & (np.asarray(after[2]) != int(RESULTS.successful))
    )


@once_per_call
def _initial(kernel, constants, step_bound, g0, m0, h, valid, save, group):
    return _setup(kernel, constants, step_bound, g0, m0, h, valid, 1, NoProgressMeter())[1]


def _save_shapes(kernel, init, save, group):
    """The shapes of one save's outputs, from the initial state (nothing computed). Traced
    from `_outputs` alone: tracing the whole set-up (the kernel's `prepare`) cost 40–60 ms
    per call for a body on SE(3), a third of a 10⁴-step run of one body. Cached by the
    kernel, `save`, `group` and the state's shapes and dtypes: tracing `_outputs` again at
    every eager call cost about 1 ms of a short call's 5–5.5 ms (one SE(3) body, 10 steps,
    best of 150), which a run cut into segments (`simulate_with_neighbor_list`,
    `stream_batch`) pays once a segment."""
    key = _hashable((kernel, save, group, abstract_key(init)))
    if key is None:  # an unhashable kernel or group: traced, not cached
        return _traced_save_shapes(kernel, init, save, group)
    return _cached_save_shapes(*key)


@functools.lru_cache(maxsize=64)
def _cached_save_shapes(kernel, save, group, key):
    return _traced_save_shapes(kernel, abstract_tree(key), save, group)


def _traced_save_shapes(kernel, init, save, group):
    batch, dtype = init[0][0].shape[0], init[1][0].dtype

    def one(state):
        return _outputs(kernel, state, _zero_counters(batch, dtype), save, group)[1]

    return eqx.filter_eval_shape(one, init)


@RunProgram
def _block(
    kernel,
    constants,
    step_bound,
    g0,
    m0,
    h,
    valid,
    save,
    group,
    progress,
    state,
    n_steps,
    save_every,
    count,
    shapes,
    size,
):
    """`count` saves of `save_every` steps each (traced), into buffers of `size` saves of
    one save's `shapes` (`_save_shapes`)."""
    setup = (kernel, constants, step_bound, g0, m0, h, valid, n_steps, progress)
    one_step, _ = _setup(*setup)
    zero_counters = _zero_counters(g0.shape[0], m0.dtype)
    # 0 at the start of a run (a repeat at a later block is not shown again), before the
    # loop: the loop starts from the step count it returns.
    state = (*state[:4], progress.report(state[4], n_steps))

    def one_save(index, carry):
        state, buffers = carry
        step = lambda _, carry: one_step(carry, None)[0]  # noqa: E731
        state, counters = jax.lax.fori_loop(0, save_every, step, (state, zero_counters))
        state, out = _outputs(kernel, state, counters, save, group)
        return state, store(buffers, index, out)

    state, buffers = jax.lax.fori_loop(0, count, one_save, (state, save_buffers(shapes, size)))
    # Batch-major here, once: what is compiled per horizon (`_join`) only concatenates. The
    # buffers past `count` are zeros, so the iterations sum over the block.
    return state, _layout(kernel, buffers)


@once_per_call
def _join(kernel, g0, m0, h, t0, n_steps, save_every, save, final, outputs):
    n_saves = n_steps // save_every
    out = {
        name: sum(x[name] for x in outputs)
        if name == "iterations"
        else jnp.concatenate([x[name] for x in outputs], axis=1)[:, :n_saves]
        for name in outputs[0]
    }
    return _solution(kernel, g0, m0, h, t0, n_steps, save_every, save, final, out)


def _layout(kernel, out):
    """The stacked per-save outputs `(T, k, B)` batch-major: `g` `(B, T, n, n)`, `m` and
    `advected` `(B, T, ·)`, the statistics `(B, T)`, and `iterations` summed, `(B,)`."""
    moved = {"iterations": jnp.sum(out["iterations"], axis=0)}
    if "g" in out:
        moved["g"] = kernel.elements(out["g"])
    for name in ("m", "advected"):
        if name in out:
            moved[name] = jnp.moveaxis(out[name], -1, 0)
    for name in ("max_iterations", "residual"):
        if name in out:
            moved[name] = out[name].T
    return moved


def _solution(kernel, g0, m0, h, t0, n_steps, save_every, save, final, out):
    """The batch's `Solution` from the final state and the per-save outputs (`_layout`)."""
    batch, dtype = g0.shape[0], m0.dtype
    _, _, result, failed_step, _ = final
    n_saves = n_steps // save_every
    # As `simulate`: t0 + h·save_every·k.
    ts = t0 + (h[:, None] if h.ndim else h) * save_every * jnp.arange(n_saves + 1, dtype=dtype)
    ts = jnp.broadcast_to(ts, (batch, n_saves + 1))
    stats = {
        "failed_step": failed_step,
        "total_newton_iterations": out["iterations"],
        "num_steps": jnp.full((batch,), n_steps),
    }
    if save.stats:
        stats["newton_iterations"] = out["max_iterations"]
        stats["residual"] = out["residual"]
    gs = ms = advected = None
    if save.g:
        # Initial state first.
        gs = jnp.concatenate([g0[:, None], out["g"]], axis=1)
    if save.m:
        ms = jnp.concatenate([m0[:, None], out["m"]], axis=1)
    if save.advected:
        advected0 = jnp.stack(kernel.advected(kernel.carried(g0)), axis=-1)
        advected = jnp.concatenate([advected0[:, None], out["advected"]], axis=1)
    return Solution(ts=ts, g=gs, m=ms, result=result, stats=stats, advected=advected)
