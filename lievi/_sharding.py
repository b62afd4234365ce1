"""Placing a batch on the local devices (`shard_batch`) or on those of every process of
JAX's multi-controller runtime (`shard_process_batch`), and reading it back
(`gather_batch`, `process_rows`). The bodies are independent: lievi adds no communication
beyond the fast path's "is any body unconverged" all-reduce per step (docs/cluster.md)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

AXIS = "batch"  # the mesh axis the bodies are split over


def _shardings(devices):
    """`(split along the batch, replicated)` over a one-axis mesh `"batch"` of `devices`."""
    mesh = jax.sharding.Mesh(np.asarray(devices), (AXIS,))
    spec = jax.sharding.PartitionSpec
    return jax.sharding.NamedSharding(mesh, spec(AXIS)), jax.sharding.NamedSharding(mesh, spec())


def shard_batch(tree, devices=None):
    """Place every array leaf of `tree` on `devices` (default: `jax.local_devices()`),
    split along its leading (batch) axis over a one-axis mesh `"batch"`; scalars are
    replicated. The batch size must be a multiple of the number of devices.
    `simulate_batch` on such inputs is partitioned by XLA, each device integrating its
    own bodies. For several processes, see `lievi.shard_process_batch`."""
    devices = jax.local_devices() if devices is None else list(devices)
    if not devices:
        raise ValueError(
            "`devices` is empty; pass at least one device (default: all local devices)."
        )
    split, replicated = _shardings(devices)

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


def shard_process_batch(tree):
    """Assemble global arrays from each process's own rows (a multi-process run).

    Under `jax.distributed.initialize()` every process calls this with **its own share**
    of the batch (the same number of rows on every process, a multiple of its local device
    count). Each array leaf becomes a global `jax.Array` over a one-axis mesh `"batch"` of
    every process's devices, its leading axis the processes' rows in process order; the
    data stay where they are. Scalars are replicated (the same value on every process).
    `simulate_batch` (or a gradient through it) on such arrays runs each process's bodies
    on its own devices; read the results with `lievi.process_rows` (this process's rows)
    or `lievi.gather_batch` (the whole batch, one all-gather).
    """
    devices = sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
    split, replicated = _shardings(devices)
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
    communication; the inverse of `lievi.shard_process_batch`); a leaf that spans no other
    process is returned whole."""

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
    """Every array leaf of `tree` whole, as NumPy arrays, on every process (a global array
    all-gathered: call it on every process, for what fits in one process's memory; else
    read `lievi.process_rows`)."""
    from jax.experimental import multihost_utils

    def whole(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x) if eqx.is_array(x) else x

    return jax.tree_util.tree_map(whole, tree)
