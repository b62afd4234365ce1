"""Runs whose horizon is not compiled in: the step loop in blocks of saves.

A `lax.scan` over `n_steps // save_every` saves compiles the step into a program whose
shapes (and trip counts) are those of the horizon: a new `n_steps` or `save_every` is a
new program, and compiling it costs as much as the first time (seconds for an implicit
step; the step's code, not the loop, is what XLA spends its time on). An eager call — one
not under `jax.jit`, `jax.grad` or `jax.vmap` — therefore runs its saves in blocks of a
fixed number of saves (`block_saves`), each block one call of one compiled program whose
trip counts (`save_every`, the saves in this block, `n_steps` for the progress meter) are
traced integers: every horizon reuses it, and only the few small programs that join the
blocks into the output are compiled per horizon.

Under a transformation the run stays one static `scan`: reverse mode cannot go through a
loop whose trip count is traced, and inside the caller's `jit` the program is compiled
once per trace anyway.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._checks import is_concrete
from ._compile import tracing

# Saves per block: a block's output buffers are `block_saves(...)` saves long whatever the
# horizon, so a block must be short enough to be cheap when few saves are used and long
# enough that the host loop over blocks (one dispatch each, ~0.1 ms) is negligible.
MAX_BLOCK_SAVES = 256
# A block's output buffers are kept under this many bytes: they are filled and reordered
# whole, used or not, so a large block costs run time on a short run of a large batch
# (measured: 128 MB buffers made 10⁴ bodies × 100 steps 1.8–2.7× slower; 4 MB, none). A
# save of more than this (≳ 4·10⁴ bodies) is a block of its own, whose steps outweigh a
# dispatch.
BLOCK_BYTES = 1 << 22


def horizon_traced(*trees) -> bool:
    """Whether a run may take the traced horizon: called eagerly (no `jit`, `grad`, `vmap`
    or other transformation is tracing the caller, so nothing can differentiate through the
    loop; without JAX's test, the static scan, always correct) with concrete inputs."""
    return not tracing() and is_concrete(*jax.tree.leaves(trees))


def block_saves(bytes_per_save: int) -> int:
    """Saves per block for saves of `bytes_per_save` bytes (a function of the shapes only,
    never of the horizon, so that a new horizon reuses the compiled block)."""
    return max(1, min(MAX_BLOCK_SAVES, BLOCK_BYTES // max(1, bytes_per_save)))


def as_count(n: int):
    """A loop bound as a traced `int32` (not a Python `int`, which `eqx.filter_jit` would
    make a static argument, compiled in)."""
    return jnp.asarray(n, jnp.int32)


def run_blocks(block, carry, n_saves: int, size: int, first=None, kept=None):
    """`carry` through `n_saves` saves, `block(carry, count)` running `count ≤ size` saves
    and returning `(carry, buffers)` with buffers `size` saves long. Returns the final carry
    and the list of each block's buffers.

    `first`: a block of the same signature tried before `block` (a program that compiles
    sooner and is right for most runs), kept while `kept(before, after)` holds for the
    carries at the start and end of each of its blocks (a host-side test, so each of its
    blocks waits for the previous one). The first block after which it does not hold is
    run again by `block` from that block's start, and so is every later one: then `block`
    is compiled too, and the run is `block`'s."""
    outputs = []
    for start in range(0, n_saves, size):
        count = as_count(min(size, n_saves - start))
        if first is not None:
            tried, buffers = first(carry, count)
            if kept(carry, tried):
                carry = tried
                outputs.append(buffers)
                continue
            first = None
        carry, buffers = block(carry, count)
        outputs.append(buffers)
    return carry, outputs


def join_blocks(outputs, n_saves: int):
    """The blocks' buffers (a list of pytrees, each leaf with a leading axis of saves) as one
    pytree of `n_saves` saves (for use inside a jit-compiled function)."""
    return jax.tree.map(lambda *xs: jnp.concatenate(xs)[:n_saves], *outputs)


def save_buffers(shapes, size: int):
    """Zero buffers of `size` saves for outputs shaped as `shapes` (a pytree of
    `jax.ShapeDtypeStruct`s of one save)."""
    return jax.tree.map(lambda s: jnp.zeros((size,) + s.shape, s.dtype), shapes)


def store(buffers, index, values):
    """`buffers` with save `index` set to `values` (same pytree structure)."""
    return jax.tree.map(lambda b, x: b.at[index].set(x), buffers, values)
