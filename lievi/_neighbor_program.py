"""The whole of a `lievi.simulate_with_neighbor_list` run as one compiled program, for a
builder that rebuilds its list on the device (`AbstractNeighborBuilder.rebuilds_on_device`).

As jax-md's users write a neighbour-list run: the segments and the rebuilds between them
inside one `lax.while_loop`, the overflow read after the run. Each segment is one traced
`simulate` call (`lievi._loop`'s step loop) on the potential with the current list, every
step saved for the stale-list check; the loop keeps the list, the builder's state and
the counts in its carry and writes each segment's saves into the run's buffers. What the
host loop (`lievi._simulate_neighbors`) decides after each segment is decided here in the
program, by the same rules: a list built at a segment's start that went stale ends the
run (`STALE`, raised by the caller), a kept list that went stale is built again and the
segment run again, a failed step ends the run with the later saves NaN. A rebuild that
overflowed (more pairs than the capacity, or a buffer of jax-md's) ends the run too: the
caller runs it again on the host, which enlarges jax-md's buffers or names `capacity`.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from ._results import RESULTS
from ._save import Save
from ._simulate import simulate

RUNNING, FAILED, STALE = 0, 1, 2


class Outcome(NamedTuple):
    """What the program returns: the run's saves and per-step statistics, and the
    neighbour-list counts; `status` (`RUNNING` at the end of a whole run), with the
    segment start and displacement of a stale list, and `overflow`."""

    g: jax.Array
    m: jax.Array
    advected: jax.Array | None
    newton_iterations: jax.Array
    residual: jax.Array
    total_newton_iterations: jax.Array
    result: jax.Array
    failed_step: jax.Array
    builds: jax.Array
    reruns: jax.Array
    pairs: jax.Array
    largest: jax.Array
    status: jax.Array
    stale_start: jax.Array
    stale_displacement: jax.Array
    overflow: jax.Array


def largest_displacement(potential, g, g_built):
    """The largest distance a site moved, over the poses `g` `(T, N, 4, 4)`, from where it
    was at `g_built` (the list's build)."""
    moved = jax.vmap(potential.flat_positions)(g) - potential.flat_positions(g_built)[None]
    return jnp.sqrt(jnp.max(jnp.sum(moved * moved, axis=-1)))


def listed_pairs(pairs, n_sites):
    """How many rows of a list are pairs (the rest is padding)."""
    return jnp.sum(pairs[:, 1] < n_sites)


@eqx.filter_jit
def run_program(
    system,
    integrator,
    g0,
    m0,
    listed0,
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
    checkpoint,
    tuning,
    progress,
) -> Outcome:
    """The run from `(g0, m0)` with the list and builder state `listed0 = (pairs, state)`
    built on the host at `g0`. `save`: what the run saves and how often (`every`);
    `rebuild_after`: a fraction of the skin (0 builds a list for every segment), `h`, `t0`
    and it traced, so that a new value reuses the program."""
    potential = where(system)
    pairs0, state0 = listed0
    dynamic0, static = eqx.partition(state0, eqx.is_array)
    n_sites = potential.sites.shape[0] * potential.sites.shape[1]
    every, R = save.every, rebuild_every
    n_saves = n_steps // every + 1
    each = Save(g=True, m=True, stats=True, advected=save.advected, every=1)

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
            forcing=None if forcing is None else forcing.steps(start, R),
            args=args,
            save=each,
            throw=False,
            checkpoint=checkpoint,
            tuning=tuning,
        )

    def rebuild(g, dynamic):
        pairs, state, overflow = builder.rebuild(potential, g, eqx.combine(dynamic, static))
        return pairs, eqx.partition(state, eqx.is_array)[0], overflow

    g0, m0 = jnp.asarray(g0), jnp.asarray(m0)
    shapes = jax.eval_shape(segment, g0, m0, pairs0, jnp.asarray(0))
    dtype = shapes.m.dtype

    def buffer(shape):
        return None if shape is None else jnp.full((n_saves, *shape.shape[1:]), jnp.nan, dtype)

    zero, false = jnp.asarray(0), jnp.asarray(False)
    carry = dict(
        segment=zero,
        g=g0,
        m=m0,
        pairs=pairs0,
        dynamic=dynamic0,
        built_at=g0,
        built_step=zero,
        fresh=false,  # a list is to be built at the segment's start
        builds=jnp.asarray(1),
        reruns=zero,
        most_pairs=listed_pairs(pairs0, n_sites),
        largest=jnp.asarray(0.0, dtype),
        status=jnp.asarray(RUNNING),
        result=jnp.asarray(RESULTS.successful, jnp.int32),
        failed_step=jnp.asarray(-1, jnp.int32),
        stale_start=zero,
        stale_displacement=jnp.asarray(0.0, dtype),
        overflow=false,
        total=jnp.zeros((), shapes.stats["total_newton_iterations"].dtype),
        saves=(buffer(shapes.g), buffer(shapes.m), buffer(shapes.advected)),
        iterations=jnp.zeros((n_steps,), shapes.stats["newton_iterations"].dtype),
        residual=jnp.zeros((n_steps,), shapes.stats["residual"].dtype),
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
        displacement = largest_displacement(potential, sol.g, built_at)
        stale = ~failed & (displacement >= builder.skin / 2)
        stale_fresh = stale & (built_step == start)
        accepted = ~stale & ~overflow  # a kept list gone stale: the segment again, fresh
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
        fresh_next = displacement >= rebuild_after * builder.skin
        status = jnp.where(
            overflow,
            c["status"],
            jnp.where(stale_fresh, STALE, jnp.where(accepted & failed, FAILED, RUNNING)),
        )
        progress.report((c["segment"] + accepted) * R, n_steps)  # repeats are dropped
        return dict(
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
            most_pairs=jnp.maximum(c["most_pairs"], listed_pairs(pairs, n_sites)),
            largest=jnp.where(ok, jnp.maximum(c["largest"], displacement), c["largest"]),
            status=status,
            result=jnp.where(accepted, sol.result, c["result"]).astype(jnp.int32),
            failed_step=jnp.where(
                accepted & failed, start + sol.stats["failed_step"], c["failed_step"]
            ).astype(jnp.int32),
            stale_start=jnp.where(stale_fresh, start, c["stale_start"]),
            stale_displacement=jnp.where(stale_fresh, displacement, c["stale_displacement"]),
            overflow=c["overflow"] | overflow,
            total=c["total"] + jnp.where(accepted, sol.stats["total_newton_iterations"], 0),
            saves=saves,
            iterations=c["iterations"].at[rows].set(sol.stats["newton_iterations"], mode="drop"),
            residual=c["residual"].at[rows].set(sol.stats["residual"], mode="drop"),
        )

    c = jax.lax.while_loop(going, one_segment, carry)
    g, m, advected = c["saves"]
    return Outcome(
        g=g,
        m=m,
        advected=advected,
        newton_iterations=jnp.max(c["iterations"].reshape(n_saves - 1, every), axis=1),
        residual=jnp.max(c["residual"].reshape(n_saves - 1, every), axis=1),
        total_newton_iterations=c["total"],
        result=c["result"],
        failed_step=c["failed_step"],
        builds=c["builds"],
        reruns=c["reruns"],
        pairs=c["most_pairs"],
        largest=c["largest"],
        status=c["status"],
        stale_start=c["stale_start"],
        stale_displacement=c["stale_displacement"],
        overflow=c["overflow"],
    )
