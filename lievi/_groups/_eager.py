"""A group's operations, called eagerly, run as one compiled program each.

Outside a transformation JAX runs a function's operations one by one, each a small
program compiled on first use: `SO3.log` of one rotation was 36 of them (0.8 s at its
first call, 1.5 ms at each later one; as one program 0.15–0.18 s, then 0.08 ms).
`compiled_when_eager` gives a group class's public operations one `eqx.filter_jit`
program each for concrete inputs (one compile per shape and dtype, then a dispatch).
Called with a tracer — under `jit`, `vmap`, `grad` or a loop, which is how the library's
own steps call them — they are traced inline as before: the library's programs do not
change.
"""

from __future__ import annotations

import functools
import inspect

import equinox as eqx
import jax

from .._checks import is_concrete


def _compiled(method):
    compiled = eqx.filter_jit(method)

    @functools.wraps(method)
    def call(self, *args, **kwargs):
        if is_concrete(*jax.tree.leaves((args, kwargs))):
            return compiled(self, *args, **kwargs)
        return method(self, *args, **kwargs)

    return call


def compiled_when_eager(cls):
    """`cls` with each public method, its own and inherited (not properties, not
    abstract), compiled whole when called with concrete inputs (module docstring)."""
    for name in dir(cls):
        method = getattr(cls, name)  # an `eqx.Module` method read from the class: the function
        if name.startswith("_") or not inspect.isfunction(method):
            continue
        if not getattr(method, "__isabstractmethod__", False):
            setattr(cls, name, _compiled(method))
    return cls
