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
from ._simulate_batch import infer_system_axis, simulate_batch
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
    unsupported = ("checkpoint", "forcing", "args", "monitor")
    opts = options("lievi.stream_batch", n_steps, locals(), deprecated, unsupported)
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
    element, momentum = system.element_shape(), system.momentum_shape()
    batch = np.shape(m0)[0] if np.ndim(m0) == 1 + len(momentum) else 0
    if batch == 0 or np.shape(m0)[1:] != momentum:
        raise ValueError(
            f"`m0` must have shape (batch, {', '.join(map(str, momentum))}) (one momentum "
            f"per body) with batch ≥ 1, got {np.shape(m0)}."
        )
    if np.shape(g0) not in ((batch, *element), element):
        raise ValueError(
            f"`g0` must have shape {(batch, *element)} or {element}, got {np.shape(g0)}."
        )
    if np.ndim(h) not in (0, 1) or (np.ndim(h) == 1 and np.shape(h)[0] != batch):
        raise ValueError(f"`h` must be a scalar or have shape ({batch},), got {np.shape(h)}.")
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
    dtype = np.dtype(state_dtype(system, np.asarray(g0[:1]), np.asarray(m0[:1]), h))
    n_saves = n_steps // every + 1
    shapes = {"g": element, "m": momentum}
    fields = {k: ((batch, n_saves, *shapes[k]), dtype.name) for k in shapes if getattr(save, k)}
    tuning, default = opts.tuning, Tuning()
    record = {
        k: getattr(tuning, k) for k in DEPRECATED[1:] if getattr(tuning, k) != getattr(default, k)
    }
    layout = StreamLayout(
        fields,
        batch,
        n_steps,
        every,
        chunk_size,
        segment_steps,
        (element, momentum),
        dtype.name,
        run_record(system, integrator, g0, m0, h, record, chunk_size),
    )
    progress = opts.progress
    worst = int(RESULTS.successful)
    writer.open(layout)
    try:
        total = float(batch) * n_steps
        done = 0.0
        for chunk in range(layout.n_chunks()):
            rows = slice(chunk * chunk_size, min(batch, (chunk + 1) * chunk_size))
            system_rows = system if system_axis is None else _rows_of(system, rows)
            state = writer.resume_state(chunk) or _initial_state(
                system_rows, system_axis, g0, m0, h, rows, element
            )
            done += (rows.stop - rows.start) * state.steps_done
            progress.show(done / total)
            while state.steps_done < n_steps:
                piece = Save(g=True, m=True, stats=False, every=every)
                run = dict(save=piece, t0=t0, system_axis=system_axis, tuning=opts.tuning)
                values, state = _segment(
                    system_rows, integrator, h, rows, state, segment_steps, run
                )
                first = state.steps_done // every - segment_steps // every
                saves = slice(first if first == 0 else first + 1, state.steps_done // every + 1)
                values = {name: values[name] for name in fields}
                writer.write(chunk, rows, saves, values, state)
                done += (rows.stop - rows.start) * segment_steps
                progress.show(done / total)
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


def _rows_of(tree, rows):
    return jax.tree.map(lambda x: x[rows] if eqx.is_array(x) else x, tree)


def _h_rows(h, rows):
    return h if np.ndim(h) == 0 else np.asarray(h)[rows]


def _mask(flags, x):
    """`flags` `(b,)` shaped to broadcast against `x` `(b, …)`."""
    return np.reshape(flags, flags.shape + (1,) * (np.ndim(x) - 1))


@eqx.filter_jit
def _valid_rows(system, system_axis, g, m, h):
    in_axes = (system.batch_axes(system_axis), 0, 0, None if np.ndim(h) == 0 else 0)
    return jax.vmap(input_valid, in_axes=in_axes)(system, g, m, h)


def _initial_state(system_rows, system_axis, g0, m0, h, rows, element) -> ChunkState:
    """The chunk's state at step 0: a body whose inputs are not admissible (`input_valid`)
    gets `RESULTS.invalid_input` and NaN, masked out from then on (`_segment`)."""
    b = rows.stop - rows.start
    g = np.asarray(
        g0[rows] if np.ndim(g0) == 1 + len(element) else np.broadcast_to(g0, (b, *element))
    )
    m = np.asarray(m0[rows])
    h_rows = _h_rows(h, rows)
    valid = np.asarray(_valid_rows(system_rows, system_axis, g, m, h_rows))
    return ChunkState(
        g=np.where(_mask(valid, g), g, np.nan),
        m=np.where(_mask(valid, m), m, np.nan),
        result=np.where(valid, RESULTS.successful, RESULTS.invalid_input).astype(np.int32),
        failed_step=np.where(valid, -1, 0).astype(np.int32),
        total_newton_iterations=np.zeros((b,), np.int64),
        steps_done=0,
    )


def _segment(system, integrator, h, rows, state, steps, run):
    """One chunk's segment from `state`: the values to write and the new state. A body
    failed before restarts from a harmless state (the identity, zero momentum, a unit
    step), masked out: NaN saves, its result, failed step and iterations kept."""
    failed = state.result != int(RESULTS.successful)
    identity = np.broadcast_to(np.eye(state.g.shape[-1], dtype=state.g.dtype), state.g.shape)
    g = np.where(_mask(failed, state.g), identity, state.g)
    m = np.where(_mask(failed, state.m), 0.0, state.m)
    h_rows = _h_rows(h, rows)
    if np.ndim(h_rows):
        h_rows = np.where(failed, 1.0, h_rows)
    solution = simulate_batch(system, integrator, g, m, h=h_rows, n_steps=steps, throw=False, **run)
    out_g = np.where(_mask(failed, solution.g), np.nan, solution.g)
    out_m = np.where(_mask(failed, solution.m), np.nan, solution.m)
    result = np.asarray(solution.result)
    failed_step = np.asarray(solution.stats["failed_step"])
    iterations = np.asarray(solution.stats["total_newton_iterations"])
    new_failure = ~failed & (result != int(RESULTS.successful))
    state = ChunkState(
        g=out_g[:, -1],
        m=out_m[:, -1],
        result=np.where(failed, state.result, result).astype(np.int32),
        failed_step=np.where(new_failure, failed_step + state.steps_done, state.failed_step).astype(
            np.int32
        ),
        total_newton_iterations=state.total_newton_iterations + np.where(failed, 0, iterations),
        steps_done=state.steps_done + steps,
    )
    # The first segment writes the initial state too; later ones start at their first save.
    skip = 0 if state.steps_done == steps else 1
    return {"g": out_g[:, skip:], "m": out_m[:, skip:]}, state
