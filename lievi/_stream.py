"""`stream_batch`: a batch whose saved output does not fit in memory, in chunks of bodies
and segments of time, each a `simulate_batch` call from the state the previous segment
ended in (a segment boundary is a save), each segment's saves handed to a writer."""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

from ._checks import check_integer, check_scalar, input_valid, state_dtype
from ._options import DEPRECATED, OPTIONS, Tuning, options
from ._progress import AbstractProgressMeter
from ._results import RESULTS
from ._save import Save
from ._simulate_batch import batch_size, infer_system_axis, simulate_batch
from ._stream_record import run_record
from ._stream_writer import AbstractStreamWriter, ChunkState, StreamLayout


def stream_batch(
    system,
    integrator,
    g0,
    m0,
    *,
    h,
    n_steps: int,
    writer: AbstractStreamWriter,
    chunk_size: int = 10_000,
    segment_steps: int | None = None,
    save: Save = OPTIONS["save"],
    t0=OPTIONS["t0"],
    throw: bool = OPTIONS["throw"],
    checkpoint: bool | int = OPTIONS["checkpoint"],
    progress_meter: AbstractProgressMeter | bool | str = OPTIONS["progress_meter"],
    forcing=OPTIONS["forcing"],
    args=OPTIONS["args"],
    monitor=OPTIONS["monitor"],
    tuning: Tuning = OPTIONS["tuning"],
    system_axis: int | None = None,
    **deprecated,
) -> None:
    """`simulate_batch` for output larger than memory: written chunk by chunk, resumable
    (docs/larger-than-memory.md).

    The batch is cut into chunks of `chunk_size` bodies and the horizon into segments of
    `segment_steps` steps; each (chunk, segment) is one `simulate_batch` call from the
    state the chunk's previous segment ended in, its saves written to `writer` as soon as
    it finishes. Memory is that of one chunk's segment; the values written equal those
    of one `simulate_batch` call, to round-off. A stopped run resumes from each chunk's
    last finished segment when called again with the same arguments and writer storage
    (the writer keeps a `lievi.ChunkState` per chunk and what defines the run,
    `StreamLayout.run`, and refuses another run with a `ValueError` naming what differs).

    **Arguments:**

    - `system`, `integrator`, `g0`, `m0`, `h`, `system_axis`: as `simulate_batch`; `g0`,
      `m0` may be NumPy memory maps (read a chunk's rows at a time).
    - `writer`: where the saves go, a `lievi.AbstractStreamWriter`, e.g.
      `lievi.NpyWriter("run/")`.
    - `chunk_size`: bodies per chunk (default 10 000).
    - `segment_steps`: steps per segment, a multiple of `save.every` dividing `n_steps`
      (default: the whole horizon).
    - `save`, `t0`, `throw`, `progress_meter`, `tuning`: the run options, as
      `lievi.simulate`. `save.g`, `save.m`: what is written (`save.stats` is ignored; the
      summary per body always is). `throw=True` raises, once everything is written, if a
      body failed. The meter shows the fraction of all body-steps done after each segment.
    - `checkpoint`, `forcing`, `args`, `monitor`: not taken (any value but the default
      is a `ValueError`).

    Saves are at `t0 + k·save.every·h`. A failed body keeps its first failure in `result`
    and `failed_step` (counted from the start) and NaN in its later saves; a body whose
    own inputs are not admissible gets `RESULTS.invalid_input` at step 0 and NaN saves,
    and the others run. Arguments shared by all bodies are checked at once (`ValueError`).
    """
    opts = options("lievi.stream_batch", n_steps, locals(), deprecated, _UNSUPPORTED)
    n_steps, save, every = opts.n_steps, opts.save, opts.save.every
    if save.advected or not (save.g or save.m):
        raise ValueError(
            f"`save` of a streamed run writes `g`, `m` or both, got {save.names()}; the "
            "summary per body (result, failed_step, total_newton_iterations) is always written."
        )
    if not isinstance(writer, AbstractStreamWriter):
        raise TypeError(
            f"`writer` must be a lievi.AbstractStreamWriter (e.g. lievi.NpyWriter(directory)), "
            f"got {type(writer).__name__}."
        )
    batch = batch_size(system, g0, m0, h)
    element, momentum = system.element_shape(), system.momentum_shape()
    if np.ndim(h) == 0:
        check_scalar("h", h, positive=True)  # shared by every body: an argument error
    chunk_size = min(check_integer("chunk_size", chunk_size, 1), batch)
    segment_steps = n_steps if segment_steps is None else segment_steps
    segment_steps = check_integer("segment_steps", segment_steps, 1)
    if segment_steps % every or n_steps % segment_steps:
        raise ValueError(
            f"`segment_steps` ({segment_steps}) must be a multiple of `save.every` "
            f"({every}) that divides `n_steps` ({n_steps}): a segment ends on a save."
        )
    system_axis = infer_system_axis(system, system_axis, batch)
    dtype = np.dtype(state_dtype(system, np.asarray(g0[:1]), np.asarray(m0[:1]), h)).name
    shapes = {"g": element, "m": momentum}
    fields = {
        k: ((batch, n_steps // every + 1, *v), dtype) for k, v in shapes.items() if getattr(save, k)
    }
    tuned = {k: getattr(opts.tuning, k) for k in DEPRECATED[1:]}
    tuned = {k: v for k, v in tuned.items() if v != getattr(Tuning(), k)}
    record = run_record(system, integrator, g0, m0, h, tuned, chunk_size)
    layout = StreamLayout(
        fields, batch, n_steps, every, chunk_size, segment_steps, (element, momentum), dtype, record
    )
    # Each segment saves both halves of the state (the next segment starts from them).
    run = dict(
        save=Save(stats=False, every=every), t0=t0, system_axis=system_axis, tuning=opts.tuning
    )
    worst, done = int(RESULTS.successful), 0
    writer.open(layout)
    try:
        for chunk in range(layout.n_chunks()):
            rows = slice(chunk * chunk_size, min(batch, (chunk + 1) * chunk_size))
            b, h_rows = rows.stop - rows.start, h if np.ndim(h) == 0 else np.asarray(h)[rows]
            system_rows = system if system_axis is None else _rows_of(system, rows)
            state = writer.resume_state(chunk)
            if state is None:
                g = g0[rows] if np.shape(g0) != element else np.broadcast_to(g0, (b, *element))
                state = _initial_state(system_rows, system_axis, np.asarray(g), m0[rows], h_rows)
            while True:  # the meter: the fraction of all body-steps done
                opts.progress.show((done + b * state.steps_done) / (batch * n_steps))
                if state.steps_done == n_steps:
                    break
                saves, values, state = _segment(
                    system_rows, integrator, h_rows, state, segment_steps, run
                )
                values = {name: values[name] for name in fields}
                writer.write(chunk, rows, saves, values, state)
            done += b * n_steps
            worst = max(worst, int(np.max(state.result)))
        writer.finish()
    finally:
        # Also when the run stops (an error, an interrupt): what was written is kept.
        writer.close()
    if throw and worst != int(RESULTS.successful):
        raise RuntimeError(
            f"lievi.stream_batch: a body failed: {RESULTS.messages[worst]} (everything is "
            "written: read each body's `result` and `failed_step`; pass throw=False not to "
            "raise.)"
        )


_UNSUPPORTED = ("checkpoint", "forcing", "args", "monitor")


def _rows_of(tree, rows):
    return jax.tree.map(lambda x: x[rows] if eqx.is_array(x) else x, tree)


def _mask(flags, x):
    """`flags` `(b,)` shaped to broadcast against `x` `(b, …)`."""
    return np.reshape(flags, flags.shape + (1,) * (np.ndim(x) - 1))


@eqx.filter_jit
def _valid_rows(system, system_axis, g, m, h):
    in_axes = (system.batch_axes(system_axis), 0, 0, None if np.ndim(h) == 0 else 0)
    return jax.vmap(input_valid, in_axes=in_axes)(system, g, m, h)


def _initial_state(system, system_axis, g, m, h) -> ChunkState:
    """A chunk at step 0: a body whose inputs are not admissible (`input_valid`) starts
    failed, `RESULTS.invalid_input` at step 0 (its saves NaN, as a failed body's)."""
    m = np.asarray(m)
    valid = np.asarray(_valid_rows(system, system_axis, g, m, h))
    result, failed_step = RESULTS.initial(valid, np)
    return ChunkState(g, m, result, failed_step, np.zeros(len(m), np.int64), 0)


def _segment(system, integrator, h, state, steps, run):
    """`(saves, values, state)`: one chunk's segment from `state`, the indices and values
    of its saves (the initial state's only in the first segment) and the state after it.
    A body failed before runs from a harmless state (the identity, zero momentum, a unit
    step), masked out: NaN saves, its result, failed step and iterations kept."""
    failed = state.result != int(RESULTS.successful)
    g = np.where(_mask(failed, state.g), np.eye(state.g.shape[-1], dtype=state.g.dtype), state.g)
    m = np.where(_mask(failed, state.m), 0.0, state.m)
    h = np.where(failed, 1.0, h) if np.ndim(h) else h
    solution = simulate_batch(system, integrator, g, m, h=h, n_steps=steps, throw=False, **run)
    out = {
        k: np.where(_mask(failed, x), np.nan, x) for k, x in (("g", solution.g), ("m", solution.m))
    }
    result, stats = np.asarray(solution.result), jax.tree.map(np.asarray, solution.stats)
    new_failure = ~failed & (result != int(RESULTS.successful))
    every, done = run["save"].every, state.steps_done
    state = ChunkState(
        out["g"][:, -1],
        out["m"][:, -1],
        np.where(failed, state.result, result).astype(np.int32),
        np.where(new_failure, stats["failed_step"] + done, state.failed_step).astype(np.int32),
        state.total_newton_iterations + np.where(failed, 0, stats["total_newton_iterations"]),
        done + steps,
    )
    # The first segment writes the initial state too; later ones start at their first save.
    skip = 0 if done == 0 else 1
    saves = slice(done // every + skip, state.steps_done // every + 1)
    return saves, {k: x[:, skip:] for k, x in out.items()}, state
