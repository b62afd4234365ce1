"""What defines a streamed run, as a record its storage keeps (`StreamLayout.run`): small
values as they are, else SHA-256 digests of what defines them — a pytree's structure and
static fields and its leaves' dtypes, shapes and bytes — so that a run resumed on that
storage is checked to be the run that wrote it."""

from __future__ import annotations

import hashlib
import importlib.metadata
import re

import equinox as eqx
import jax
import numpy as np

# Memory addresses in the `repr` of a static field (a function) change between processes.
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _version() -> str:
    try:
        return importlib.metadata.version("lievi")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def tree_digest(tree) -> str:
    """A digest of a pytree's structure, static fields and leaves (non-arrays by `repr`)."""
    digest = hashlib.sha256()
    leaves, treedef = jax.tree.flatten(tree)
    digest.update(_ADDRESS.sub("", str(treedef)).encode())
    for leaf in leaves:
        if eqx.is_array(leaf) or isinstance(leaf, np.generic):
            leaf = np.asarray(leaf)
            digest.update(f"{leaf.dtype}{leaf.shape}".encode())
            digest.update(np.ascontiguousarray(leaf).tobytes())
        else:
            digest.update(_ADDRESS.sub("", repr(leaf)).encode())
    return "sha256:" + digest.hexdigest()


def rows_digest(x, block: int) -> str:
    """A digest of an array's dtype, shape and bytes, read `block` rows at a time."""
    digest = hashlib.sha256(f"{np.result_type(x)}{np.shape(x)}".encode())
    if np.ndim(x) == 0:
        digest.update(np.asarray(x).tobytes())
    for start in range(0, np.shape(x)[0] if np.ndim(x) else 0, block):
        digest.update(np.ascontiguousarray(x[start : start + block]).tobytes())
    return "sha256:" + digest.hexdigest()


def run_record(system, integrator, g0, m0, h, options: dict, block: int) -> dict[str, str]:
    """What defines a streamed run besides its layout, each a short string (`g0`, `m0`
    and a per-body `h` read `block` rows at a time)."""
    return {
        "system": tree_digest(system),
        "integrator": tree_digest(integrator),
        "g0": rows_digest(g0, block),
        "m0": rows_digest(m0, block),
        "h": repr(float(h)) if np.ndim(h) == 0 else rows_digest(h, block),
        "options": repr(sorted(options.items())),
        "lievi": _version(),
    }
