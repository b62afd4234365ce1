"""`stream_batch`: a batch whose saved output does not fit in memory, in chunks of bodies
and segments of time, each segment's saves handed to a writer as it finishes.

Each piece is one `simulate_batch` call on a chunk of bodies for `segment_steps` steps,
from the state the previous segment ended in. The step depends on the state and `h` alone
(an unforced, autonomous run), and a segment boundary is a save, where `simulate_batch`
does what it does at every save (e.g. puts a float32 element back on the group), so the
segmented run computes the same iterates as one `simulate_batch` call over the horizon.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

from ._checks import check_integer, check_scalar, input_valid, state_dtype
from ._options import OPTIONS, Tuning, options
from ._progress import AbstractProgressMeter
from ._results import RESULTS
from ._save import Save
from ._simulate_batch import infer_system_axis, simulate_batch
from ._stream_record import run_record
from ._stream_writer import AbstractStreamWriter, ChunkState, StreamLayout


def _check_chunking(n_steps, every, chunk_size, segment_steps, batch):
    chunk_size = min(check_integer("chunk_size", chunk_size, 1), batch)
    segment_steps = n_steps if segment_steps is None else segment_steps
    segment_steps = check_integer("segment_steps", segment_steps, 1)
    if segment_steps % every or n_steps % segment_steps:
        raise ValueError(
            f"`segment_steps` ({segment_steps}) must be a multiple of `save.every` "
            f"({every}) that divides `n_steps` ({n_steps}): a segment ends on a save."
        )
    return chunk_size, segment_steps


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
    """`simulate_batch` for output larger than memory: written chunk by chunk, resumable.

    The batch is cut into chunks of `chunk_size` bodies and the horizon into segments of
    `segment_steps` steps; each (chunk, segment) is one `simulate_batch` call, started
    from the state the chunk's previous segment ended in, whose saves go to `writer` as
    soon as it finishes. Memory is that of one chunk's segment (its saved steps and the
    compiled loop's buffers), whatever the batch and the horizon. The values written
    equal those of one `simulate_batch` call on the whole batch and horizon, to round-off.

    A stopped run (killed, out of time) resumes from the last finished segment of each
    chunk: call `stream_batch` again with the same arguments and writer storage (e.g. the
    same `lievi.NpyWriter` directory). The state a chunk resumes from is `(g, m)` after
    its last finished segment, kept by the writer with the steps done and the per-body
    result so far (`lievi.ChunkState`). What defines the run — the layout, and the
    system, the integrator, `g0`, `m0`, `h`, the options and lievi's version, as values
    or digests (`StreamLayout.run`) — goes to the writer, which refuses to continue
    another run with a `ValueError` naming what differs.

    **Arguments:**

    - `system`, `integrator`, `g0`, `m0`, `h`, `system_axis`: as `simulate_batch`, also
      for systems of several bodies (`m0` `(batch, N, 6)` for `lievi.RigidBodies`); `g0`,
      `m0` may be NumPy memory maps: only one chunk's rows are read at a time (and once,
      a chunk at a time, for the run's record).
    - `writer`: where the saves go, e.g. `lievi.NpyWriter("run/")`; any
      `lievi.AbstractStreamWriter`.
    - `chunk_size`: bodies per chunk (default 10 000).
    - `segment_steps`: steps per segment, a multiple of `save.every` dividing `n_steps`
      (default: the whole horizon). Bounds the memory of a chunk's saves and the work
      lost when a run stops.
    - `save`, `t0`, `throw`, `progress_meter`, `tuning`: the options of every run
      function, as `lievi.simulate` (the same defaults). `save.g`, `save.m`: what is
      written (the chunk's state `(g, m)` is always carried, so a potential with an
      advected parameter runs its `(Π, g)` algorithm); the per-save statistics are not
      written (`save.stats` is ignored), the summary per body always is. `throw=True`
      raises, once everything is written, if a body failed; with `throw=False` the
      per-body `result` written says it. The progress meter (its shorthands labelled
      `lievi.stream_batch`) shows the fraction of all body-steps done after each
      finished segment (the chunks' own runs report nothing).
    - `checkpoint`, `forcing`, `args`, `monitor`: not taken by a streamed run (it is not
      differentiated, its forcing would not be streamed, and an invariant's reference
      is per run); any value but the default is a `ValueError`.

    Time: the saves of a body are at `t = t0 + k·save.every·h`, `k = 0, …,
    n_steps/save.every`, as in `simulate_batch`. A body that fails keeps its first failure
    in `result` and `failed_step` (the step counted from the start) and NaN in its later
    saves. A body whose own inputs are not admissible (a NaN in its `m0`, a `g0` off the
    group, its `h` or its system's parameters: the checks of `simulate_batch`) gets
    `RESULTS.invalid_input` at step 0 and NaN saves, and the others run. Arguments
    shared by all bodies (shapes, a scalar `h`, the options) are checked at once, as
    `ValueError`s.
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
    chunk_size, segment_steps = _check_chunking(n_steps, every, chunk_size, segment_steps, batch)
    system_axis = infer_system_axis(system, system_axis, batch)
    dtype = np.dtype(state_dtype(system, np.asarray(g0[:1]), np.asarray(m0[:1]), h))
    n_saves = n_steps // every + 1
    fields = {}
    if save.g:
        fields["g"] = ((batch, n_saves, *element), dtype.name)
    if save.m:
        fields["m"] = ((batch, n_saves, *momentum), dtype.name)
    knobs = {name: getattr(opts.tuning, name) for name in ("fast", "fixed_iterations", "unroll")}
    record = {name: value for name, value in knobs.items() if value != getattr(Tuning(), name)}
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
            system_rows = _rows_of(system, rows, system_axis)
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


def _h_rows(h, rows):
    return h if np.ndim(h) == 0 else np.asarray(h)[rows]


def _mask(flags, x):
    """`flags` `(b,)` shaped to broadcast against `x` `(b, …)`."""
    return np.reshape(flags, flags.shape + (1,) * (np.ndim(x) - 1))


@eqx.filter_jit
def _valid_rows(system, system_axis, g, m, h):
    """`input_valid` of each body of a chunk, as one compiled program."""
    in_axes = (system.batch_axes(system_axis), 0, 0, None if np.ndim(h) == 0 else 0)
    return jax.vmap(input_valid, in_axes=in_axes)(system, g, m, h)


def _initial_state(system_rows, system_axis, g0, m0, h, rows, element) -> ChunkState:
    """The chunk's state at step 0. A body whose inputs are not admissible (its system,
    `g0` in the group, finite `m0`, a positive normal `h`: `input_valid`, the checks
    `simulate_batch` makes) gets `RESULTS.invalid_input` at step 0 and NaN, and is
    masked out from then on (`_segment`), so one bad row does not stop the others."""
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


def _rows_of(tree, rows, axis):
    """The chunk's rows of a batch of systems (`axis=0`), or the shared system (`None`)."""
    if axis is None:
        return tree
    return jax.tree.map(lambda x: x[rows] if eqx.is_array(x) else x, tree)


def _segment(system, integrator, h, rows, state, steps, run):
    """Run one chunk (`system`: its rows) for one segment from `state` (`run`: the
    options of its `simulate_batch` call): the values to write and the new state.

    A body that failed in an earlier segment, or whose inputs were not admissible,
    restarts from a harmless state (the identity, zero momentum, a unit step) that is
    masked out: its saves are NaN and its result, failed step and iteration count stay
    those of its failure."""
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
