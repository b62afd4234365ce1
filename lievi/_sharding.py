"""Placing a batch on devices: the local ones (`shard_batch`), or those of every process of
a multi-process run (`shard_process_batch`), and reading it back (`gather_batch`,
`process_rows`).

A multi-process run is JAX's own multi-controller runtime: every process runs the same
program after `jax.distributed.initialize()`, and a global `jax.Array` spans the devices of
all processes. lievi adds no communication of its own: the bodies are independent, so the
only collectives are the fast path's "is any body unconverged" reduction (one boolean
all-reduce per step) and the ones the caller asks for (a reduction in a loss, a gather).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

AXIS = "batch"  # the mesh axis the bodies are split over


def _batch_mesh(devices) -> jax.sharding.Mesh:
    return jax.sharding.Mesh(np.asarray(devices), (AXIS,))


def shard_batch(tree, devices=None):
    """Place every array leaf of `tree` on `devices`, split along its leading (batch) axis.

    Builds a one-axis `jax.sharding.Mesh` named `"batch"` over `devices` (default: all
    local devices, `jax.local_devices()`) and puts each array with a
    `NamedSharding(mesh, PartitionSpec("batch"))`. `simulate_batch` on sharded inputs is
    then partitioned by XLA: each device integrates its own bodies (the bodies do not
    interact; the only communication is the fast path's "is any body unconverged" test).
    Scalars are replicated. The batch size must be a multiple of the number of devices.
    For a batch spread over several processes, see `lievi.shard_process_batch`.
    """
    devices = jax.local_devices() if devices is None else list(devices)
    if not devices:
        raise ValueError(
            "`devices` is empty; pass at least one device (default: all local devices)."
        )
    mesh = _batch_mesh(devices)
    split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(AXIS))
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())

    def place(x):
        if not eqx.is_array(x):
            return x
        if jnp.ndim(x) == 0:
            return jax.device_put(x, replicated)
        if jnp.shape(x)[0] % len(devices):
            raise ValueError(
                f"the batch axis ({jnp.shape(x)[0]}) must be a multiple of the number of "
                f"devices ({len(devices)}); pad the batch or pass fewer `devices`."
            )
        return jax.device_put(x, split)

    return jax.tree_util.tree_map(place, tree)


def process_mesh() -> jax.sharding.Mesh:
    """The one-axis mesh over the devices of every process, grouped by process in process
    order: process `p`'s rows come `p`-th in the global batch."""
    devices = sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
    return _batch_mesh(devices)


def shard_process_batch(tree):
    """Assemble global arrays from each process's own rows (a multi-process run).

    Under `jax.distributed.initialize()` every process calls this with **its own share**
    of the batch (the same number of rows on every process, a multiple of its local device
    count). Each array leaf becomes a global `jax.Array` over a one-axis mesh `"batch"` of
    the devices of all processes (`jax.make_array_from_process_local_data`): its leading
    axis is the concatenation of the processes' rows in process order (process 0's
    first). The data stay where they are; nothing is sent. Scalars are replicated (every
    process must pass the same value).

    `simulate_batch`, `jax.grad` of a loss over it, … on such arrays run each process's
    bodies on its own devices. Read the results with `lievi.process_rows` (this process's
    rows, no communication) or `lievi.gather_batch` (the whole batch on every process,
    one all-gather). With one process this is `lievi.shard_batch(tree)`.
    """
    mesh = process_mesh()
    split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(AXIS))
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    local = len(jax.local_devices())

    def place(x):
        if not eqx.is_array(x):
            return x
        x = np.asarray(x)
        if x.ndim == 0:
            return jax.make_array_from_process_local_data(replicated, x)
        if x.shape[0] == 0 or x.shape[0] % local:
            raise ValueError(
                f"this process's rows ({x.shape[0]}) must be a positive multiple of its "
                f"local device count ({local}); pad the share of the batch."
            )
        global_shape = (x.shape[0] * jax.process_count(),) + x.shape[1:]
        return jax.make_array_from_process_local_data(split, x, global_shape)

    return jax.tree_util.tree_map(place, tree)


def process_rows(tree):
    """This process's rows of every batched array leaf of `tree`, as NumPy arrays (no
    communication): the inverse of `lievi.shard_process_batch`. A leaf that spans no other
    process (a scalar, a replicated or a local array) is returned whole."""

    def rows(x):
        if not isinstance(x, jax.Array) or x.is_fully_addressable or x.ndim == 0:
            return np.asarray(x) if eqx.is_array(x) else x
        # One copy of each block of rows (replicas have `replica_id > 0`), in order.
        shards = sorted(
            (s for s in x.addressable_shards if s.replica_id == 0),
            key=lambda s: s.index[0].start or 0,
        )
        return np.concatenate([np.asarray(s.data) for s in shards])

    return jax.tree_util.tree_map(rows, tree)


def gather_batch(tree):
    """Every array leaf of `tree` whole, as NumPy arrays, on every process: a global array
    over several processes is all-gathered (`multihost_utils.process_allgather`, one
    collective moving the whole array to every process); any other array is read as it is.
    Call it on every process (a collective), and only for what fits in one process's
    memory: for large outputs read `lievi.process_rows` instead."""
    from jax.experimental import multihost_utils

    def whole(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x) if eqx.is_array(x) else x

    return jax.tree_util.tree_map(whole, tree)
