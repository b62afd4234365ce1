"""World-frame state in, world-frame state out, for rigid bodies on SE(3)
(`lievi.RigidBodySE3`, `lievi.RigidBodies`).

lievi's state is a pose `g = [[R, p], [0, 1]]` and a **body-frame** momentum `m = (Π, P)`
(docs/theory/conventions.md, docs/se3.md): `R` maps body coordinates to world
coordinates, `p` is the world position of the body origin (the centre of mass for a body
in vacuum), and `m = M ξ` is the Legendre map (paper §2) of the body velocity
`ξ = g⁻¹ġ = (Ω, v)`, whose parts are the world angular velocity `ω` and the world
velocity `ṗ` of the origin seen from the body:

    Ω = Rᵀ ω,    v = Rᵀ ṗ,    (Π, P) = M (Ω, v).

For a body in vacuum, `M = diag(J, m 1)`: `Π = J Ω` (the angular momentum about the centre
of mass, body frame) and `P = m Rᵀ ṗ` (the linear momentum, body frame); the world ones are
`R Π` and `R P = m ṗ`. `state_from_world` applies these, `state_to_world` inverts them
with the system's own inverse Legendre map (`velocity`), so a full 6×6 tensor (added mass,
an origin off the centre of mass) is handled the same way.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import check_finite, is_concrete, membership_tolerance
from ._groups._se3 import SE3
from ._groups._so3 import SO3
from ._systems._base import AbstractLieSystem


class WorldState(NamedTuple):
    """A rigid body's state in world coordinates (`lievi.state_to_world`), each with the
    leading axes of the state it came from and a body axis for a system of several.

    **Attributes:**

    - `positions`: the world position `p` of each body origin, `(…, 3)`.
    - `velocities`: its world velocity `ṗ`, `(…, 3)`.
    - `attitudes`: the rotation `R` from body to world coordinates, `(…, 3, 3)`.
    - `angular_velocities`: the world (spatial) angular velocity `ω = R Ω`, `(…, 3)`.
    """

    positions: Float[Array, "*batch 3"]
    velocities: Float[Array, "*batch 3"]
    attitudes: Float[Array, "*batch 3 3"]
    angular_velocities: Float[Array, "*batch 3"]


def state_from_world(
    system: AbstractLieSystem,
    positions: Float[Array, "*batch 3"],
    velocities: Float[Array, "*batch 3"],
    attitudes: Float[Array, "*batch 3 3"],
    angular_velocities: Float[Array, "*batch 3"],
) -> tuple[Float[Array, "*batch 4 4"], Float[Array, "*batch 6"]]:
    """lievi's state `(g, m)` of a rigid body (or of each body of several) given in world
    coordinates (module docstring: `Ω = Rᵀω`, `v = Rᵀṗ`, `m = M (Ω, v)`).

    **Arguments:**

    - `system`: a system on SE(3) — `lievi.RigidBodySE3`, `lievi.RigidBodies` — whose
      kinetic tensor turns velocities into momenta (its `legendre`).
    - `positions`: world positions `p` of the body origins (the centres of mass for bodies
      in vacuum), `(*batch, 3)` for one body, `(*batch, N, 3)` for `N` bodies.
    - `velocities`: their world velocities `ṗ`, shaped as `positions`.
    - `attitudes`: rotation matrices `R` (body to world, the active rotation of scipy's
      `Rotation.as_matrix()`), `(*batch, 3, 3)` or `(*batch, N, 3, 3)`; quaternions
      convert with `lievi.quaternion_xyzw_to_matrix` / `lievi.quaternion_wxyz_to_matrix`.
    - `angular_velocities`: world (spatial) angular velocities `ω`, shaped as `positions`.

    Any leading `batch` axes give a batch of states, as `lievi.simulate_batch` takes them.

    **Returns:** `(g, m)`: poses `(*batch, [N,] 4, 4)` and body momenta `(Π, P)`
    `(*batch, [N,] 6)`.
    """
    bodies = _bodies(system)
    arrays = {
        "positions": (positions, (3,)),
        "velocities": (velocities, (3,)),
        "attitudes": (attitudes, (3, 3)),
        "angular_velocities": (angular_velocities, (3,)),
    }
    batch = _batch_shape(arrays, bodies)
    dtype = jnp.result_type(*(x for x, _ in arrays.values()), float)
    R = jnp.asarray(attitudes, dtype)
    _check_rotations(R)
    return _from_world(
        system,
        len(batch),
        jnp.asarray(positions, dtype),
        jnp.asarray(velocities, dtype),
        R,
        jnp.asarray(angular_velocities, dtype),
    )


def state_to_world(
    system: AbstractLieSystem, g: Float[Array, "*batch 4 4"], m: Float[Array, "*batch 6"]
) -> WorldState:
    """The world-frame state of lievi's `(g, m)`: the inverse of `state_from_world`
    (`ξ = M⁻¹m` by the system's `velocity`, then `ω = RΩ`, `ṗ = Rv`).

    **Arguments:**

    - `system`: a system on SE(3), as for `state_from_world`.
    - `g`, `m`: states with any leading axes — one state, a trajectory `sol.g`, `sol.m`
      of `lievi.simulate`, a batch of trajectories — each of the system's
      `element_shape()` and `momentum_shape()`.

    **Returns:** a `WorldState` (`positions`, `velocities`, `attitudes`,
    `angular_velocities`) with the leading axes of `g`.
    """
    bodies = _bodies(system)
    arrays = {"g": (g, (4, 4)), "m": (m, (6,))}
    batch = _batch_shape(arrays, bodies)
    dtype = jnp.result_type(g, m, float)
    return _to_world(system, len(batch), jnp.asarray(g, dtype), jnp.asarray(m, dtype))


def _bodies(system) -> tuple[int, ...]:
    """The body axes of one state: `()` for one body, `(N,)` for several. Raises
    `ValueError` unless `system` is on SE(3) (its elements have a translation)."""
    if not isinstance(system, AbstractLieSystem) or (
        system.group.translation(system.group.identity()) is None
    ):
        name = type(system).__name__
        group = type(getattr(system, "group", None)).__name__
        raise ValueError(
            f"`system` must be a rigid body on SE(3) (`lievi.RigidBodySE3`, "
            f"`lievi.RigidBodies`), got {name} on {group}. On SO(3) the state is the "
            "attitude `g = R` and the body momentum `m = system.legendre(R.T @ ω)`."
        )
    return tuple(system.element_shape()[:-2])


def _batch_shape(arrays, bodies) -> tuple[int, ...]:
    """The leading axes every array shares in front of one state's `bodies + core`;
    `ValueError` naming the first array that does not fit."""
    batch = None
    for name, (x, core) in arrays.items():
        shape, tail = tuple(jnp.shape(x)), bodies + core
        if len(shape) < len(tail) or shape[len(shape) - len(tail) :] != tail:
            raise ValueError(
                f"`{name}` must have shape (*batch, {', '.join(map(str, tail))}), got {shape}."
            )
        lead = shape[: len(shape) - len(tail)]
        if batch is None:
            batch = lead
        elif lead != batch:
            raise ValueError(
                f"`{name}` has leading axes {lead}, the arrays before it {batch}: give every "
                "array the same batch axes."
            )
        check_finite(name, x)
    return batch


def _check_rotations(R) -> None:
    if not is_concrete(R):
        return
    with jax.ensure_compile_time_eval():
        defect = float(jnp.max(SO3.membership_defect(R))) if R.size else 0.0
    bound = membership_tolerance(R.dtype)
    if not np.isfinite(defect) or defect > bound:
        raise ValueError(
            f"`attitudes` must be rotation matrices (orthogonal, det +1): membership defect "
            f"{defect:.3g} > {bound:.2g}. Build them with `lievi.SO3.exp`, "
            "`lievi.quaternion_xyzw_to_matrix`, or orthonormalise with `lievi.SO3.project`."
        )


def _each_state(fn, x, batch_ndim: int):
    """`fn` of one state applied over the `batch_ndim` leading axes of `x`."""
    for _ in range(batch_ndim):
        fn = jax.vmap(fn)
    return fn(x)


def _rotate(R, x):
    return jnp.einsum("...ij,...j->...i", R, x)


def _rotate_back(R, x):
    return jnp.einsum("...ji,...j->...i", R, x)


@eqx.filter_jit
def _from_world(system, batch_ndim, p, p_dot, R, omega):
    # The body velocity ξ = g⁻¹ġ = (Rᵀω, Rᵀṗ) (twist order of `lievi.SE3`), then m = Mξ.
    xi = jnp.concatenate([_rotate_back(R, omega), _rotate_back(R, p_dot)], axis=-1)
    m = _each_state(system.legendre, xi, batch_ndim)
    return SE3.from_rotation_translation(R, p), m


@eqx.filter_jit
def _to_world(system, batch_ndim, g, m):
    xi = _each_state(system.velocity, m, batch_ndim)
    R = SE3.rotation(g)
    return WorldState(
        positions=SE3.translation(g),
        velocities=_rotate(R, xi[..., 3:]),
        attitudes=R,
        angular_velocities=_rotate(R, xi[..., :3]),
    )
