"""`simulate_with_neighbor_list`: one run of a system whose site potential sums over a
neighbour list, in segments with a rebuild of the list between them.

A neighbour list built with a skin holds every pair within the cut-off only while no site
has moved more than half the skin (`lievi/_systems/_neighbors.py`), so a long run is cut
into segments of `rebuild_every` steps, each one `simulate` call from the state the last
ended in, on the potential with a list built at that state. With a builder that rebuilds
on the device (both of lievi's) the whole run, segments and rebuilds, is one compiled
program (`lievi._neighbor_program`); with one that builds on the host, or where a rebuild
overflowed, the segments are run from the host, here, by the same rules. The list is data of the
potential (a fixed-shape int array), so every segment runs the same compiled step. After
each segment the largest site displacement since the build is checked against `skin/2`
at every step of the segment: a list that went stale is an error naming the fix, never
a silently wrong force. With `rebuild_after` a list is kept across segments until a site
has moved that fraction of the skin, and a segment in which it went stale is run again
with a list built at its start. A segment boundary is a save, where `simulate` changes
nothing in float64 (as for `lievi.stream_batch`), so the run equals one `simulate` call
on the all-pairs cut-off potential to round-off.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import check_integer
from ._loop import raise_if_failed
from ._neighbor_program import (
    STALE,
    largest_displacement,
    listed_pairs,
    run_program,
)
from ._options import OPTIONS, Tuning, options
from ._results import RESULTS
from ._save import Save
from ._simulate import simulate
from ._solution import Solution
from ._systems._neighbors import AbstractNeighborBuilder

_largest_displacement = eqx.filter_jit(largest_displacement)
_listed_pairs = jax.jit(listed_pairs)


@jax.jit
def _take(arrays, index):
    """The saves `index` of each array (one program for all, not one gather each)."""
    return jax.tree.map(lambda x: x[index], arrays)


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
    `rebuild_every` steps and checked.

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
      (`neighbor_reruns` counts them). Fewer builds where they are the cost (jax-md's
      cell list on a CPU: about a second each for 10⁴ bodies), the same result; a
      smaller `f` trades builds for fewer reruns.
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

    With `lievi.BruteForceNeighbors` or `lievi.JaxMDNeighbors` the whole run — the
    segments, the rebuilds between them (jax-md's compiled `update`), the checks — is one
    compiled program, as jax-md's users write a neighbour-list run: the first list is
    built on the host (it sizes `capacity`), the others inside the program. A builder
    that builds on the host only (`AbstractNeighborBuilder.rebuilds_on_device` false)
    has its segments called from the host, by the same rules and with the same result.

    **Returns:** a `Solution` over the whole horizon, as one `simulate` call gives it,
    with `stats` adding `neighbor_builds` (the lists built), `neighbor_pairs` (the most
    pairs a list held), `neighbor_capacity`, `neighbor_max_displacement` (the largest
    site displacement from a list's build, to compare with `skin/2`) and
    `neighbor_reruns` (segments run again with a fresh list, `rebuild_after`).

    **Raises:** `RuntimeError` if a site moved `skin/2` or more within a segment from a
    list built at its start (the list may have missed a pair: pass a smaller
    `rebuild_every` or a larger `skin`);
    `ValueError` (from the builder) if a rebuilt list has more pairs than its
    `capacity` (a rebuild inside the program that overflowed, its own capacity or
    jax-md's buffers, is done again from the host, which enlarges jax-md's buffers or
    raises this). With `throw=False` a failed step (`RESULTS`) ends the run: the result
    and `failed_step` are reported and the later saves are NaN, as in `simulate`.
    """
    label = "lievi.simulate_with_neighbor_list"
    opts = options(label, n_steps, locals(), deprecated, unsupported=("monitor",))
    n_steps, save, forcing = opts.n_steps, opts.save, opts.forcing
    save_every = save.every
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
    run = dict(
        h=h,
        t0=t0,
        n_steps=n_steps,
        rebuild_every=rebuild_every,
        save=save,
        rebuild_after=rebuild_after,
        forcing=forcing,
        args=args,
        checkpoint=checkpoint,
        tuning=opts.tuning,
        progress=opts.progress,
    )
    if builder.rebuilds_on_device:
        potential = where(system)
        pairs, state = builder.build(potential, g0)
        if builder.capacity is None:  # sized on the first build, then fixed
            builder = dataclasses.replace(builder, capacity=pairs.shape[0])
        # Traced: a new step, start time or fraction reuses the compiled program.
        dtype = jnp.result_type(m0)
        traced = dict(
            h=jnp.asarray(h, dtype),
            t0=jnp.asarray(t0, dtype),
            rebuild_after=jnp.asarray(0.0 if rebuild_after is None else rebuild_after, dtype),
        )
        outcome = run_program(
            system, integrator, g0, m0, (pairs, state), builder=builder, where=where,
            **{**run, **traced},
        )  # fmt: skip
        # A rebuild that overflowed: the run again from the host, whose builds enlarge
        # jax-md's buffers or raise naming `capacity`.
        if not bool(outcome.overflow):
            solution = _solution(outcome, builder, save, h, t0, n_steps, rebuild_every)
            return raise_if_failed(solution, "lievi.simulate", "a step") if throw else solution
    return _run_on_host(
        system, integrator, g0, m0, builder=builder, where=where, throw=throw, **run
    )


def _solution(outcome, builder, save: Save, h, t0, n_steps: int, rebuild_every: int):
    """The `Solution` of a run of the compiled program, or the stale list's error."""
    if int(outcome.status) == STALE:
        start = int(outcome.stale_start)
        _stale(start, start + rebuild_every, float(outcome.stale_displacement), builder.skin)
    n_saves = n_steps // save.every + 1
    stats = {
        "failed_step": outcome.failed_step,
        "total_newton_iterations": outcome.total_newton_iterations,
        "num_steps": jnp.asarray(n_steps),
        "neighbor_builds": outcome.builds,
        "neighbor_pairs": outcome.pairs,
        "neighbor_capacity": jnp.asarray(builder.capacity),
        "neighbor_max_displacement": outcome.largest,
        "neighbor_reruns": outcome.reruns,
    }
    if save.stats:
        stats["newton_iterations"] = outcome.newton_iterations
        stats["residual"] = outcome.residual
    return Solution(
        t0 + h * save.every * jnp.arange(n_saves, dtype=outcome.m.dtype),
        outcome.g if save.g else None,
        outcome.m if save.m else None,
        outcome.result,
        stats,
        outcome.advected if save.with_advected() else None,
    )


def _stale(start: int, end: int, displacement: float, skin: float):
    raise RuntimeError(
        f"The neighbour list went stale in steps {start}–{end}: a site moved "
        f"{displacement:.3g} since the list was built, at least half the skin "
        f"({skin / 2:.3g}), so a pair within the cut-off may be missing. Pass a smaller "
        "`rebuild_every` or a larger `skin` to the builder."
    )


def _run_on_host(
    system,
    integrator,
    g0,
    m0,
    *,
    builder,
    where,
    h,
    t0,
    n_steps: int,
    rebuild_every: int,
    save: Save,
    rebuild_after,
    forcing,
    args,
    throw,
    checkpoint,
    tuning,
    progress,
) -> Solution:
    """The run with its segments called from the host: for a builder that builds on the
    host only, or after a rebuild overflowed in the compiled program."""
    save_every = save.every
    # Every step of a segment saved (the displacement check reads them), on `g` and `m`.
    each = Save(g=True, m=True, stats=True, advected=save.advected, every=1)
    segment_options = dict(save=each, throw=throw, checkpoint=checkpoint, tuning=tuning)
    potential = where(system)
    g, m = jnp.asarray(g0), jnp.asarray(m0)
    h_value = float(h)
    n_sites = potential.sites.shape[0] * potential.sites.shape[1]
    # Counts and displacements stay on the device until the end: a segment's only
    # transfers to the host are its result code and its largest displacement.
    pieces, builds, reruns, pair_counts, largest = [], 0, 0, [], 0.0
    failure, state, listed, built_at, built_step = None, None, None, None, None
    for segment in range(n_steps // rebuild_every):
        start = segment * rebuild_every
        while True:
            # A new list: the first, after a stale or used-up one, or every segment.
            if listed is None or (rebuild_after is None and built_step != start):
                pairs, state = builder.build(potential, g, state)
                if builder.capacity is None:  # sized on the first build, then fixed
                    builder = dataclasses.replace(builder, capacity=pairs.shape[0])
                builds += 1
                pair_counts.append(_listed_pairs(pairs, n_sites))
                listed = eqx.tree_at(where, system, potential.from_builder(pairs))
                built_at, built_step = g, start
            sol = simulate(
                listed,
                integrator,
                g,
                m,
                h=h,
                n_steps=rebuild_every,
                t0=t0 + start * h_value,
                forcing=None if forcing is None else forcing.steps(start, rebuild_every),
                args=args,
                **segment_options,
            )
            if int(sol.result) != RESULTS.successful:
                break
            displacement = float(_largest_displacement(potential, sol.g, built_at))
            if displacement < builder.skin / 2:
                break
            if built_step == start:
                _stale(start, start + rebuild_every, displacement, builder.skin)
            # A list kept from an earlier segment went stale: build one here, run again.
            listed, reruns = None, reruns + 1
        if int(sol.result) != RESULTS.successful:
            failure = (int(sol.result), start + int(sol.stats["failed_step"]))
            pieces.append(_kept(sol, start, save_every))
            break
        largest = max(largest, displacement)
        if rebuild_after is not None and displacement >= rebuild_after * builder.skin:
            # Enough of the margin used that the next segment may go stale: build a new
            # list at its start rather than risk running it twice.
            listed = None
        pieces.append(_kept(sol, start, save_every))
        g, m = _take((sol.g, sol.m), -1)  # one program, not one dispatch each
        progress.show((start + rebuild_every) / n_steps)
    joined = _join(pieces, h, t0, n_steps, save_every, failure)
    stats = dict(
        joined.stats,
        neighbor_builds=jnp.asarray(builds),
        neighbor_pairs=jnp.max(jnp.stack(pair_counts)),
        neighbor_capacity=jnp.asarray(builder.capacity),
        neighbor_max_displacement=jnp.asarray(largest),
        neighbor_reruns=jnp.asarray(reruns),
    )
    if not save.stats:
        del stats["newton_iterations"], stats["residual"]
    return Solution(
        joined.ts,
        joined.g if save.g else None,
        joined.m if save.m else None,
        joined.result,
        stats,
        joined.advected if save.with_advected() else None,
    )


def _kept(sol: Solution, start: int, save_every: int) -> Solution:
    """A segment from step `start`, saved at every step: its saves at the run's save
    times (steps that are multiples of `save_every`; the segment's first state is the
    previous segment's last, kept only for the first segment), and its per-step
    statistics whole (`_join` reduces them over each `save_every` steps)."""
    steps = start + np.arange(sol.ts.shape[0])
    keep = np.flatnonzero((steps % save_every == 0) & ((steps > start) | (start == 0)))
    ts, g, m, advected = _take((sol.ts, sol.g, sol.m, sol.advected), jnp.asarray(keep))
    return Solution(ts, g, m, sol.result, sol.stats, advected)


def _join(pieces, h, t0, n_steps: int, save_every: int, failure) -> Solution:
    """One `Solution` over the horizon from the segments' (NaN-padded after a failure
    that ended the run early)."""
    n_saves = n_steps // save_every + 1

    def joined(field):
        parts = [getattr(p, field) for p in pieces]
        if parts[0] is None:
            return None
        whole = jnp.concatenate(parts)
        missing = n_saves - whole.shape[0]
        pad = jnp.full((missing, *whole.shape[1:]), jnp.nan, whole.dtype)
        return jnp.concatenate([whole, pad])

    def stat(name):
        """Per step, over the steps run (zero-padded), then the most over each interval
        between saves, as `simulate` reports it."""
        whole = jnp.concatenate([p.stats[name] for p in pieces])
        whole = jnp.concatenate([whole, jnp.zeros((n_steps - whole.shape[0],), whole.dtype)])
        return jnp.max(whole.reshape(n_saves - 1, save_every), axis=1)

    m = joined("m")
    result, failed_step = (RESULTS.successful, -1) if failure is None else failure
    stats = {
        "newton_iterations": stat("newton_iterations"),
        "residual": stat("residual"),
        "failed_step": jnp.asarray(failed_step, jnp.int32),
        "total_newton_iterations": sum(p.stats["total_newton_iterations"] for p in pieces),
        "num_steps": jnp.asarray(n_steps),
    }
    return Solution(
        ts=t0 + h * save_every * jnp.arange(n_saves, dtype=m.dtype),
        g=joined("g"),
        m=m,
        result=jnp.asarray(result, jnp.int32),
        stats=stats,
        advected=joined("advected"),
    )
