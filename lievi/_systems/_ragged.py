"""Bodies with different numbers of points or sites, as one padded array.

The couplings of several bodies (`lievi.MutualGravity`, `lievi.SitePotential`) take their
points as arrays `(N, k, …)`: one `k` for all bodies, so that the pair sums are fixed-shape
array operations that compile once. Bodies of `k_i ≤ k` points are padded to `k`: a
padding point of gravity has mass 0, a padding site of a site potential is `False` in its
`mask`; either takes part in no pair. `stack_bodies` pads a list of per-body arrays.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def stack_bodies(name: str, per_body, fill=0, item_shape: tuple[int, ...] = (), dtype=float):
    """`per_body` as one array `(N, k, *item_shape)`: an array already, or a list of `N`
    per-body arrays `(k_i, *item_shape)` padded with `fill` to `k = max k_i`. Also returns
    the mask `(N, k)` of the entries given (NumPy; all `True` for an array). `dtype`:
    the values' dtype (`None`: as given, e.g. for integer site types)."""
    if not isinstance(per_body, (list, tuple)):
        values = jnp.asarray(per_body, dtype)  # traced values too
        return values, np.ones(values.shape[:2], bool)
    rows = [np.asarray(row) if dtype is None else np.asarray(row, dtype) for row in per_body]
    for i, row in enumerate(rows):
        if row.ndim != 1 + len(item_shape) or row.shape[1:] != item_shape:
            want = ", ".join(["k_i", *map(str, item_shape)])
            raise ValueError(
                f"`{name}[{i}]` must have shape ({want}) (one body's entries), got {row.shape}."
            )
    k = max((len(row) for row in rows), default=0)
    dtype = np.result_type(*rows) if dtype is None and rows else dtype
    values = np.full((len(rows), k, *item_shape), fill, dtype)
    mask = np.zeros((len(rows), k), bool)
    for i, row in enumerate(rows):
        values[i, : len(row)] = row
        mask[i, : len(row)] = True
    return jnp.asarray(values), mask
