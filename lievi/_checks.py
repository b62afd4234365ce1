"""Argument checks that raise `ValueError` naming the argument and the fix.

Checks on *values* (positivity, orthogonality, NaN) run only when the value is concrete,
i.e. when the function is called eagerly. Under `jit`/`vmap`/`grad` the values are
tracers; there a NaN or an impossible step still surfaces through the `result` code of
the solve (see `lievi.RESULTS`), never as a silent number.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def check_shape(name: str, x, shape: tuple[int, ...], what: str = "") -> None:
    if tuple(jnp.shape(x)) != tuple(shape):
        hint = f" ({what})" if what else ""
        raise ValueError(f"`{name}` must have shape {tuple(shape)}{hint}, got {tuple(jnp.shape(x))}.")


def check_finite(name: str, x) -> None:
    if is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
        raise ValueError(f"`{name}` contains NaN or inf; pass finite values.")


def check_spd(name: str, matrix) -> None:
    """Symmetric positive definite, for a concrete (…, k, k) array."""
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
