"""Conversions between lievi's matrices and jaxlie's group objects (jaxlie is optional).

lievi represents SO(3) by 3×3 rotation matrices and SE(3) by homogeneous 4×4 matrices
`[[R, p], [0, 1]]`; jaxlie stores a unit quaternion (and a translation). Twists differ in
order: lievi's `(ω, v)` (rotation first, like `lievi.SO3`), jaxlie's `(v, ω)`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float


def _jaxlie():
    try:
        import jaxlie
    except ImportError as error:  # an optional dependency
        raise ImportError(
            "lievi.to_jaxlie/from_jaxlie need jaxlie: `pip install jaxlie`."
        ) from error
    return jaxlie


def to_jaxlie(g: Float[Array, "*batch n n"]):
    """A lievi group element as a jaxlie object.

    **Arguments:** `g`: rotation matrices `(…, 3, 3)` or homogeneous matrices `(…, 4, 4)`.

    **Returns:** a `jaxlie.SO3` or `jaxlie.SE3` (with the same leading batch axes).
    """
    jaxlie = _jaxlie()
    g = jnp.asarray(g)
    if g.shape[-2:] == (3, 3):
        return jaxlie.SO3.from_matrix(g)
    if g.shape[-2:] == (4, 4):
        return jaxlie.SE3.from_matrix(g)
    raise ValueError(
        f"`g` must be rotation matrices (…, 3, 3) or homogeneous matrices (…, 4, 4), got "
        f"shape {g.shape}."
    )


def from_jaxlie(x) -> Float[Array, "*batch n n"]:
    """A `jaxlie.SO3` or `jaxlie.SE3` as lievi's rotation or homogeneous matrix."""
    jaxlie = _jaxlie()
    if not isinstance(x, (jaxlie.SO3, jaxlie.SE3)):
        raise ValueError(f"`x` must be a jaxlie.SO3 or jaxlie.SE3, got {type(x).__name__}.")
    return x.as_matrix()


def twist_to_jaxlie(xi: Float[Array, "*batch 6"]) -> Float[Array, "*batch 6"]:
    """lievi's twist `(ω, v)` in jaxlie's order `(v, ω)`: `jaxlie.SE3.exp(twist_to_jaxlie(ξ))`
    is `lievi.SE3.exp(ξ)`."""
    xi = jnp.asarray(xi)
    return jnp.concatenate([xi[..., 3:], xi[..., :3]], axis=-1)


def twist_from_jaxlie(tangent: Float[Array, "*batch 6"]) -> Float[Array, "*batch 6"]:
    """jaxlie's tangent `(v, ω)` in lievi's order `(ω, v)`."""
    tangent = jnp.asarray(tangent)
    return jnp.concatenate([tangent[..., 3:], tangent[..., :3]], axis=-1)
