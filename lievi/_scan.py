"""The checkpointed scan of a run: `lax.scan` in `jax.checkpoint`-ed segments.

Reverse mode through a run of `n` steps stores one carry per segment and recomputes the
steps inside a segment on the way back: memory `O(n/segment + segment)` instead of `O(n)`
(`simulate(..., checkpoint=...)`, `simulate_batch(..., checkpoint=...)`).
"""

from __future__ import annotations

import functools

import jax
import numpy as np


def checkpoint_segment(checkpoint, n_steps: int, save_every: int) -> int | None:
    """Steps per `jax.checkpoint`-ed segment, or `None` for no checkpointing."""
    if checkpoint is False or checkpoint is None:
        return None
    # A segment either lies inside one save interval or spans whole save intervals.
    n_saves = n_steps // save_every
    allowed = sorted(
        {d for d in range(1, save_every + 1) if save_every % d == 0}
        | {save_every * d for d in range(1, n_saves + 1) if n_saves % d == 0}
    )
    if checkpoint is True:
        # √N segments of √N steps minimise stored states + one segment's internals.
        return min(allowed, key=lambda c: abs(np.log(c) - 0.5 * np.log(n_steps)))
    if (
        isinstance(checkpoint, bool)
        or not isinstance(checkpoint, (int, np.integer))
        or checkpoint not in allowed
    ):
        raise ValueError(
            f"`checkpoint` must be True, False, or a segment length in steps that divides "
            f"`save_every` ({save_every}) or is a multiple of it dividing `n_steps` ({n_steps}); "
            f"got {checkpoint!r}. Pass checkpoint=True to choose one near √n_steps."
        )
    return int(checkpoint)


def scan_in_segments(body, carry, length: int, segment: int | None, xs=None, unroll: int = 1):
    """`lax.scan(body, carry, xs, length)`, in `jax.checkpoint`-ed chunks of `segment` steps
    (reverse mode then stores the carry at chunk boundaries only). `unroll`: as `lax.scan`'s.

    `prevent_cse=False`: the checkpointed chunk is itself the body of a scan, where JAX's
    common-subexpression guard is not needed (see `jax.checkpoint`) and would only cost."""
    if segment is None or segment >= length:
        return jax.lax.scan(body, carry, xs, length=length, unroll=min(unroll, length))

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def chunk(carry, xs):
        return jax.lax.scan(body, carry, xs, length=segment, unroll=min(unroll, segment))

    xs = jax.tree.map(lambda x: x.reshape((length // segment, segment) + x.shape[1:]), xs)
    carry, ys = jax.lax.scan(chunk, carry, xs, length=length // segment)
    return carry, jax.tree.map(lambda y: y.reshape((length,) + y.shape[2:]), ys)
