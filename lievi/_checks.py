"""Argument checks that raise `ValueError` naming the argument and the fix.

Checks on *values* (positivity, orthogonality, NaN) raise only when the value is
concrete, i.e. when the function is called eagerly. Under `jit`/`vmap`/`grad` the values
are tracers; there the same checks run inside the computation (`input_valid`) and a bad
value gives `RESULTS.invalid_input` for that body — never a silent number.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def check_shape(name: str, x, shape: tuple[int, ...], what: str = "") -> None:
    if tuple(jnp.shape(x)) != tuple(shape):
        hint = f" ({what})" if what else ""
        raise ValueError(
            f"`{name}` must have shape {tuple(shape)}{hint}, got {tuple(jnp.shape(x))}."
        )


def check_finite(name: str, x) -> None:
    if is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
        raise ValueError(f"`{name}` contains NaN or inf; pass finite values.")


def check_spd(name: str, matrix) -> None:
    """Symmetric positive definite, for a concrete (…, k, k) array (the dtype is checked
    for traced arrays too; their values are checked by `input_valid`)."""
    check_real_dtype(name, matrix)
    if not is_concrete(matrix):
        return
    m = np.asarray(matrix, dtype=float)
    check_finite(name, m)
    if not np.allclose(m, np.swapaxes(m, -1, -2), rtol=1e-10, atol=1e-12 * np.abs(m).max()):
        raise ValueError(f"`{name}` must be symmetric; symmetrise it as (I + Iᵀ)/2.")
    if np.any(np.linalg.eigvalsh(m) <= 0):
        raise ValueError(
            f"`{name}` must be positive definite (all eigenvalues > 0); got eigenvalues "
            f"{np.linalg.eigvalsh(m)}."
        )


def check_scalar(name: str, x, *, positive: bool = False) -> None:
    """Reject strings, bools, complex and non-scalar values; concrete values must be
    finite (and, with `positive`, a normal number > 0)."""
    if isinstance(x, (str, bytes)) or isinstance(x, (bool, np.bool_)):
        raise ValueError(f"`{name}` must be a real number, got {x!r}.")
    dtype = jnp.result_type(x)
    if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
        raise ValueError(f"`{name}` must be a real number, got dtype {dtype}.")
    if jnp.ndim(x) != 0:
        raise ValueError(f"`{name}` must be a scalar, got shape {jnp.shape(x)}.")
    if is_concrete(x):
        check_finite(name, x)
        if positive:
            value = float(x)
            tiny = float(jnp.finfo(jnp.result_type(x, float)).tiny)
            if not value > 0:
                raise ValueError(f"`{name}` must be > 0, got {value}; pass a positive step size.")
            if value < tiny:
                raise ValueError(
                    f"`{name}` = {value} is subnormal (below {tiny:.3g}); pass a normal "
                    "positive step size."
                )


def check_real_dtype(name: str, x) -> None:
    """Reject complex, bool and non-numeric arrays (they would be cast silently)."""
    if isinstance(x, (str, bytes)):
        dtype = None
    else:
        dtype = np.asarray(x).dtype if isinstance(x, (list, tuple)) else jnp.result_type(x)
    if dtype is None or not (
        jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)
    ):
        raise ValueError(
            f"`{name}` must hold real numbers, got {'a string' if dtype is None else dtype}."
        )


def step_size_valid(h):
    """Traceable: `h` is a finite normal number > 0 (per body)."""
    tiny = jnp.finfo(jnp.result_type(h, float)).tiny
    return jnp.isfinite(h) & (h >= tiny)


def input_valid(system, g0, m0, h, t0=0.0):
    """Traceable validity of a run's inputs: the system's parameters, `g0` in the group,
    finite `m0`, `t0`, and a positive normal `h`. A boolean array (`simulate` turns
    `False` into `RESULTS.invalid_input`)."""
    return (
        system.parameters_valid()
        & system.element_valid(g0)
        & jnp.all(jnp.isfinite(m0))
        & step_size_valid(h)
        & jnp.isfinite(t0)
    )


def as_int(value):
    """NumPy integers become Python ints (a static field must not hold a NumPy scalar)."""
    return int(value) if isinstance(value, np.integer) else value


def check_integer(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"`{name}` must be an integer ≥ {minimum}, got {value!r}.")
    return int(value)


def state_dtype(system, *arrays):
    """The dtype a run computes in: NumPy promotion of the state, `h` and the system's
    floating-point parameters (a float64 inertia with a float32 state runs in float64;
    for float32 throughout, pass float32 parameters too)."""
    params = [x for x in jax.tree.leaves(system) if eqx.is_inexact_array(x)]
    return jnp.result_type(*arrays, *params, float)
