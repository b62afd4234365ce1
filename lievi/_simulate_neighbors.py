"""`simulate_with_neighbor_list`: a run in segments with a rebuild of the neighbour list
between them, as one compiled program (as jax-md's users write one; docs/rigid-bodies.md).

Each segment is a traced `simulate` call on the potential with the current list, every step
saved for the stale-list check; a segment boundary is a save, where `simulate` changes
nothing in float64, so the run equals one `simulate` call on the all-pairs cut-off
potential to round-off.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import check_integer
from ._loop import raise_if_failed
from ._options import OPTIONS, Tuning, options
from ._results import RESULTS
from ._save import Save
from ._simulate import simulate
from ._solution import Solution
from ._systems._neighbors import AbstractNeighborBuilder

RUNNING, FAILED, STALE = 0, 1, 2


def _default_where(system):
    return system.potential


def simulate_with_neighbor_list(
    system,
    integrator,
    g0,
    m0,
    *,
    h,
    n_steps: int,
    rebuild_every: int,
    builder: AbstractNeighborBuilder,
    where: Callable = _default_where,
    rebuild_after: float | None = None,
    save: Save = OPTIONS["save"],
    t0=OPTIONS["t0"],
    throw: bool = OPTIONS["throw"],
    checkpoint: bool | int = OPTIONS["checkpoint"],
    progress_meter=OPTIONS["progress_meter"],
    forcing=OPTIONS["forcing"],
    args=OPTIONS["args"],
    monitor=OPTIONS["monitor"],
    tuning: Tuning = OPTIONS["tuning"],
    **deprecated,
) -> Solution:
    """`simulate` with the neighbour list of a `lievi.SitePotential` rebuilt every
    `rebuild_every` steps and checked (docs/rigid-bodies.md).

    **Arguments:**

    - `system`, `integrator`, `g0`, `m0`, `h`, `n_steps`: as `simulate` (`g0`
      `(N, 4, 4)`, `m0` `(N, 6)` for `lievi.RigidBodies`).
    - `rebuild_every`: steps per segment, dividing `n_steps`. Each segment runs with
      every step saved (for the displacement check), thinned to every `save.every`-th
      step of the run as it finishes: memory of one segment's steps plus the saves.
    - `builder`: `lievi.BruteForceNeighbors(skin)` (no dependency, `O((N k)²)` per build)
      or `lievi.JaxMDNeighbors(skin)` (jax-md's cell list, `O(N k)`), with the list's
      `capacity` (`None`: sized on the first build, then kept).
    - `rebuild_after`: `None` (default) builds a list for every segment. A fraction `f`
      of the skin (`0 < f ≤ 1/2`, e.g. `0.25`) keeps a list across segments: a new one
      is built at the start of the segment after a site has moved `f·skin` since the
      last build, and a segment in which the list went stale anyway (a site moved
      `skin/2`) is run again from its start with a list built there
      (`neighbor_reruns` counts them).
    - `where`: where the `SitePotential` sits in `system` (default
      `lambda system: system.potential`), for `eqx.tree_at`; the potential needs a
      `cutoff` (and may have a `box`); its own `neighbors` are replaced.
    - `save`, `t0`, `throw`, `checkpoint`, `progress_meter`, `forcing`, `args`,
      `tuning`: the options of every run function, as `simulate` (the same defaults); a
      `lievi.Control` has the whole run's `n_steps` rows, each segment runs on its own
      (`AbstractForcing.steps`); `checkpoint` and `tuning` apply to each segment's run;
      the progress meter shows the fraction done after each segment. `monitor` is not
      taken (an invariant's reference would be each segment's start): any value but
      `None` is a `ValueError`.

    **Returns:** a `Solution` over the whole horizon, as one `simulate` call gives it,
    with `stats` adding `neighbor_builds` (the lists built), `neighbor_pairs` (the most
    pairs a list held), `neighbor_capacity`, `neighbor_max_displacement` (the largest
    site displacement from a list's build, to compare with `skin/2`) and
    `neighbor_reruns` (segments run again with a fresh list, `rebuild_after`).

    **Raises:** `RuntimeError` if a site moved `skin/2` or more within a segment from a
    list built at its start (the list may have missed a pair: pass a smaller
    `rebuild_every` or a larger `skin`); `ValueError` (from the builder) if a list has
    more pairs than its `capacity`. With `throw=False` a failed step (`RESULTS`) ends the
    run: the result and `failed_step` are reported and the later saves are NaN, as in
    `simulate`.
    """
    label = "lievi.simulate_with_neighbor_list"
    opts = options(label, n_steps, locals(), deprecated, unsupported=("monitor",))
    n_steps, save, forcing = opts.n_steps, opts.save, opts.forcing
    rebuild_every = check_integer("rebuild_every", rebuild_every, 1)
    if n_steps % rebuild_every:
        raise ValueError(
            f"`rebuild_every` ({rebuild_every}) must divide `n_steps` ({n_steps}): the "
            "segments between rebuilds are of equal length (one compiled step)."
        )
    if rebuild_after is not None and not 0 < rebuild_after <= 0.5:
        raise ValueError(
            f"`rebuild_after` must be None or a fraction of the skin in (0, 1/2], got "
            f"{rebuild_after!r}; e.g. 0.25."
        )
    if not isinstance(builder, AbstractNeighborBuilder):
        raise TypeError(
            "`builder` must be a neighbour-list builder (lievi.BruteForceNeighbors(skin) or "
            f"lievi.JaxMDNeighbors(skin)), got {type(builder).__name__}."
        )
    if forcing is not None:  # the whole run's data, once (each segment checks its own)
        forcing.check(system, n_steps, jnp.result_type(m0), args)
    potential = where(system)
    # The first list on the host: it sizes `capacity` (then fixed) and jax-md's buffers.
    pairs, state = builder.build(potential, g0)
    if builder.capacity is None:
        builder = dataclasses.replace(builder, capacity=pairs.shape[0])
    static = eqx.partition(state, eqx.is_array)[1]
    dtype = jnp.result_type(m0)
    fraction = 0.0 if rebuild_after is None else rebuild_after
    run = dict(
        builder=builder,
        where=where,
        h=jnp.asarray(h, dtype),
        t0=jnp.asarray(t0, dtype),
        n_steps=n_steps,
        rebuild_every=rebuild_every,
        save=save,
        rebuild_after=jnp.asarray(fraction, dtype),
        forcing=forcing,
        args=args,
        checkpoint=checkpoint,
        tuning=opts.tuning,
        progress=opts.progress,
    )
    carry = None
    while True:
        carry, ts, most = _program(system, integrator, g0, m0, (pairs, state), carry, run)
        if not bool(carry["overflow"]):
            break
        # A rebuild overflowed: the list again on the host, where the loop stopped.
        state = eqx.combine(carry["dynamic"], static)
        pairs, state = builder.build(potential, carry["g"], state)
    if int(carry["status"]) == STALE:
        start = int(carry["stale_start"])
        raise RuntimeError(
            f"The neighbour list went stale in steps {start}–{start + rebuild_every}: a "
            f"site moved {float(carry['stale_displacement']):.3g} since the list was "
            f"built, at least half the skin ({builder.skin / 2:.3g}), so a pair within "
            "the cut-off may be missing. Pass a smaller `rebuild_every` or a larger "
            "`skin` to the builder."
        )
    solution = _solution(carry, ts, most, builder, save, n_steps)
    return raise_if_failed(solution, label, "a step") if throw else solution


def _solution(c, ts, most, builder, save: Save, n_steps: int) -> Solution:
    """The `Solution` of the program's final loop state `c`, save times `ts` and
    statistics per save `most`."""
    g, m, advected = c["saves"]
    stats = {
        "failed_step": c["failed_step"],
        "total_newton_iterations": c["total"],
        "num_steps": jnp.asarray(n_steps),
        "neighbor_builds": c["builds"],
        "neighbor_pairs": c["most_pairs"],
        "neighbor_capacity": jnp.asarray(builder.capacity),
        "neighbor_max_displacement": c["largest"],
        "neighbor_reruns": c["reruns"],
    }
    if save.stats:
        stats["newton_iterations"], stats["residual"] = most["iterations"], most["residual"]
    return Solution(
        ts,
        g if save.g else None,
        m if save.m else None,
        c["result"],
        stats,
        advected if save.with_advected() else None,
    )


@eqx.filter_jit
def _program(system, integrator, g0, m0, listed, carry, run):
    """The run's loop state at its end, or where a rebuild overflowed (`overflow`): from
    `(g0, m0)` (`carry` `None`) or from `carry`, the state where an earlier call stopped,
    with the list and builder state `listed = (pairs, state)` built on the host at the
    state's poses. A list built at a segment's start that went stale ends the run
    (`STALE`), a kept list that went stale is built again and the segment run again, a
    failed step ends the run with the later saves NaN (`FAILED`). `run`: the options
    (traced where arrays: a new `h`, `t0` or fraction reuses the program)."""
    builder, where, h, t0, n_steps = (run[k] for k in ("builder", "where", "h", "t0", "n_steps"))
    potential = where(system)
    pairs0, state0 = listed
    n_sites = potential.sites.shape[0] * potential.sites.shape[1]
    save, R, progress = run["save"], run["rebuild_every"], run["progress"]
    every = save.every

    def listed_pairs(pairs):  # the rows of a list that are pairs (the rest is padding)
        return jnp.sum(pairs[:, 1] < n_sites)

    n_saves = n_steps // every + 1
    each = Save(g=True, m=True, stats=True, advected=save.advected, every=1)
    dynamic0, static = eqx.partition(state0, eqx.is_array)

    def segment(g, m, pairs, start):
        listed = eqx.tree_at(where, system, potential.from_builder(pairs))
        return simulate(
            listed,
            integrator,
            g,
            m,
            h=h,
            n_steps=R,
            t0=t0 + start * h,
            forcing=None if run["forcing"] is None else run["forcing"].steps(start, R),
            args=run["args"],
            save=each,
            throw=False,
            checkpoint=run["checkpoint"],
            tuning=run["tuning"],
        )

    def rebuild(g, dynamic):
        pairs, state, overflow = builder.rebuild(potential, g, eqx.combine(dynamic, static))
        return pairs, eqx.partition(state, eqx.is_array)[0], overflow

    if carry is None:
        g0, m0 = jnp.asarray(g0), jnp.asarray(m0)
        shapes = jax.eval_shape(segment, g0, m0, pairs0, jnp.asarray(0))
        dtype = shapes.m.dtype

        def buffer(shape):
            return None if shape is None else jnp.full((n_saves, *shape.shape[1:]), jnp.nan, dtype)

        zero = jnp.asarray(0)
        carry = dict(
            segment=zero,
            g=g0,
            m=m0,
            builds=zero,
            reruns=zero,
            most_pairs=zero,
            largest=jnp.asarray(0.0, dtype),
            status=jnp.asarray(RUNNING),
            result=jnp.asarray(RESULTS.successful, jnp.int32),
            failed_step=jnp.asarray(-1, jnp.int32),
            stale_start=zero,
            stale_displacement=jnp.asarray(0.0, dtype),
            total=jnp.zeros((), shapes.stats["total_newton_iterations"].dtype),
            saves=(buffer(shapes.g), buffer(shapes.m), buffer(shapes.advected)),
            iterations=jnp.zeros((n_steps,), shapes.stats["newton_iterations"].dtype),
            residual=jnp.zeros((n_steps,), shapes.stats["residual"].dtype),
        )
    # The list built on the host, at the poses of the segment the loop starts with.
    carry = dict(
        carry,
        pairs=pairs0,
        dynamic=dynamic0,
        built_at=carry["g"],
        built_step=carry["segment"] * R,
        fresh=jnp.asarray(False),  # a list is to be built at the segment's start
        builds=carry["builds"] + 1,
        most_pairs=jnp.maximum(carry["most_pairs"], listed_pairs(pairs0)),
        overflow=jnp.asarray(False),
    )

    def going(c):
        return (c["segment"] < n_steps // R) & (c["status"] == RUNNING) & ~c["overflow"]

    def one_segment(c):
        start = c["segment"] * R
        fresh = c["fresh"]
        pairs, dynamic, overflow = jax.lax.cond(
            fresh,
            lambda: rebuild(c["g"], c["dynamic"]),
            lambda: (c["pairs"], c["dynamic"], jnp.asarray(False)),
        )
        built_at = jnp.where(fresh, c["g"], c["built_at"])
        built_step = jnp.where(fresh, start, c["built_step"])
        sol = segment(c["g"], c["m"], pairs, start)
        failed = sol.result != RESULTS.successful
        # The largest distance a site moved in the segment from the list's build.
        moved = jax.vmap(potential.flat_positions)(sol.g) - potential.flat_positions(built_at)
        displacement = jnp.sqrt(jnp.max(jnp.sum(moved * moved, axis=-1)))
        stale = ~failed & (displacement >= builder.skin / 2)
        stale_fresh = stale & (built_step == start)
        accepted = ~stale  # a kept list gone stale: the segment again, fresh
        # The segment's saves at the run's save times (its first state is the previous
        # segment's last, written only for the first segment); index `n_saves` is dropped.
        steps = start + jnp.arange(R + 1)
        kept = accepted & (steps % every == 0) & ((steps > start) | (start == 0))
        index = jnp.where(kept, steps // every, n_saves)
        saves = tuple(
            None if b is None else b.at[index].set(x, mode="drop")
            for b, x in zip(c["saves"], (sol.g, sol.m, sol.advected))
        )
        rows = jnp.where(accepted, start + jnp.arange(R), n_steps)
        ok = accepted & ~failed
        # Enough of the margin used that the next segment may go stale (always, for a
        # fraction 0: a list for every segment).
        fresh_next = displacement >= run["rebuild_after"] * builder.skin
        status = jnp.where(stale_fresh, STALE, jnp.where(accepted & failed, FAILED, RUNNING))
        progress.report((c["segment"] + accepted) * R, n_steps)  # repeats are dropped
        new = dict(
            segment=c["segment"] + accepted,
            g=jnp.where(ok, sol.g[-1], c["g"]),
            m=jnp.where(ok, sol.m[-1], c["m"]),
            pairs=pairs,
            dynamic=dynamic,
            built_at=built_at,
            built_step=built_step,
            fresh=jnp.where(ok, fresh_next, stale),
            builds=c["builds"] + fresh,
            reruns=c["reruns"] + (stale & ~stale_fresh),
            most_pairs=jnp.maximum(c["most_pairs"], listed_pairs(pairs)),
            largest=jnp.where(ok, jnp.maximum(c["largest"], displacement), c["largest"]),
            status=status,
            result=jnp.where(accepted, sol.result, c["result"]).astype(jnp.int32),
            failed_step=jnp.where(
                accepted & failed, start + sol.stats["failed_step"], c["failed_step"]
            ).astype(jnp.int32),
            stale_start=jnp.where(stale_fresh, start, c["stale_start"]),
            stale_displacement=jnp.where(stale_fresh, displacement, c["stale_displacement"]),
            overflow=overflow,
            total=c["total"] + jnp.where(accepted, sol.stats["total_newton_iterations"], 0),
            saves=saves,
            iterations=c["iterations"].at[rows].set(sol.stats["newton_iterations"], mode="drop"),
            residual=c["residual"].at[rows].set(sol.stats["residual"], mode="drop"),
        )
        # An overflowed rebuild: the state as the segment began, for the host's list.
        stopped = dict(c, overflow=overflow)
        return jax.tree.map(lambda a, b: jnp.where(overflow, a, b), stopped, new)

    c = jax.lax.while_loop(going, one_segment, carry)
    # The statistics as `simulate` reports them: the most over each interval between saves.
    ts = t0 + h * every * jnp.arange(n_saves, dtype=c["largest"].dtype)
    most = {
        k: jnp.max(c[k].reshape(n_saves - 1, every), axis=1) for k in ("iterations", "residual")
    }
    return c, ts, most
