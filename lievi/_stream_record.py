"""What defines a streamed run (`lievi.stream_batch`), as a record its storage keeps.

A run resumed on existing storage must be the run that wrote it: the same physics (the
system and the integrator), the same initial states, step sizes and horizon, the same
dtype and options, and the same lievi. `run_record` writes these as a JSON-able dict
of short strings: values where they are small (`h` a scalar, the options), else digests
(SHA-256) of the bytes that define them. A pytree's digest covers its array leaves'
dtypes, shapes and bytes and its structure with every static field (an integrator's
chart, a system's group; a function held in a field by its name), so two systems that
compute differently have different records.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import re

import equinox as eqx
import jax
import numpy as np

# Memory addresses in the `repr` of a static field (a function, a jitted function): they
# change from one process to the next, and a resumed run is another process.
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _version() -> str:
    try:
        return importlib.metadata.version("lievi")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def tree_digest(tree) -> str:
    """A digest of a pytree: its structure and static fields, its leaves' dtypes, shapes
    and bytes (non-array leaves by `repr`)."""
    digest = hashlib.sha256()
    leaves, treedef = jax.tree.flatten(tree)
    digest.update(_ADDRESS.sub("", str(treedef)).encode())
    for leaf in leaves:
        if eqx.is_array(leaf) or isinstance(leaf, np.generic):
            _update(digest, np.asarray(leaf))
        else:
            digest.update(_ADDRESS.sub("", repr(leaf)).encode())
    return "sha256:" + digest.hexdigest()


def rows_digest(x, block: int) -> str:
    """A digest of an array's dtype, shape and bytes, read `block` rows at a time (`x` may
    be a memory map larger than memory)."""
    digest = hashlib.sha256(f"{np.result_type(x)}{np.shape(x)}".encode())
    if np.ndim(x) == 0:
        digest.update(np.asarray(x).tobytes())
    for start in range(0, np.shape(x)[0] if np.ndim(x) else 0, block):
        digest.update(np.ascontiguousarray(x[start : start + block]).tobytes())
    return "sha256:" + digest.hexdigest()


def _update(digest, x: np.ndarray) -> None:
    digest.update(f"{x.dtype}{x.shape}".encode())
    digest.update(np.ascontiguousarray(x).tobytes())


def run_record(system, integrator, g0, m0, h, options: dict, block: int) -> dict[str, str]:
    """What defines a streamed run besides its layout (`StreamLayout`: shapes, horizon,
    dtype, chunking): `{"system", "integrator", "g0", "m0", "h", "options", "lievi"}`,
    each a short string. `g0`, `m0` (and a per-body `h`) are read `block` rows at a
    time."""
    return {
        "system": tree_digest(system),
        "integrator": tree_digest(integrator),
        "g0": rows_digest(g0, block),
        "m0": rows_digest(m0, block),
        "h": repr(float(h)) if np.ndim(h) == 0 else rows_digest(h, block),
        "options": repr(sorted(options.items())),
        "lievi": _version(),
    }
