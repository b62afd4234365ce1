"""Placing a batch on the local devices (`shard_batch`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def shard_batch(tree, devices=None):
    """Place every array leaf of `tree` on `devices`, split along its leading (batch) axis.

    Builds a one-axis `jax.sharding.Mesh` named `"batch"` over `devices` (default: all
    local devices, `jax.local_devices()`) and puts each array with a
    `NamedSharding(mesh, PartitionSpec("batch"))`. `simulate_batch` on sharded inputs is
    then partitioned by XLA: each device integrates its own bodies (the bodies do not
    interact; the only communication is the fast path's "is any body unconverged" test).
    Scalars are replicated. The batch size must be a multiple of the number of devices.
    """
    devices = jax.local_devices() if devices is None else list(devices)
    if not devices:
        raise ValueError(
            "`devices` is empty; pass at least one device (default: all local devices)."
        )
    mesh = jax.sharding.Mesh(np.asarray(devices), ("batch",))
    split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
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
