"""Joints between two rigid bodies: holonomic constraints on a pair of poses.

A joint connects a *parent* pose `g_p = [[R_p, x_p], [0, 1]]` (a body, or the world:
`g_p = I`) and a *child* pose `g_c`, each body's origin at its centre of mass. Its
constraint `Φ(g_p, g_c) = 0` is written in length units, so that "satisfied to `ε`
relative to the link length" reads the same for every joint (docs/articulated.md):

- `BallJoint` (3 equations): the joint point, `a_p` in the parent's frame and `a_c` in
  the child's, is the same point in space, `x_p + R_p a_p − x_c − R_c a_c = 0`.
- `HingeJoint` (5 equations): a ball joint whose child also keeps its axis `n_c` (child
  frame) along the parent's `n_p` (parent frame): with `u₁, u₂` an orthonormal pair
  perpendicular to `n_p`, `ℓ (R_p u_α)·(R_c n_c) = 0`, `α = 1, 2`, the length `ℓ` the
  system's length scale (so these equations are in length units too).

Each joint also gives its constraint's derivative along the group in closed form
(`jacobian`: the rows of the constraint Jacobian of `lievi.ArticulatedBodies`, for the
perturbations `g ↦ g exp(ε η̂)`, `η = (ω, v)`, of the parent and of the child), which
`tests/test_articulated.py` checks against autodiff of `residual`.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_real_dtype, is_concrete


def _vector(name: str, value) -> Array:
    check_real_dtype(name, value)
    value = jnp.asarray(value, jnp.result_type(value, float))
    if value.shape != (3,):
        raise ValueError(f"`{name}` must be a 3-vector, got shape {value.shape}.")
    return value


def _axis(name: str, value) -> Array:
    value = _vector(name, value)
    if is_concrete(value) and not np.linalg.norm(np.asarray(value)) > 0:
        raise ValueError(
            f"`{name}` has zero length: a hinge needs the direction of its axis (a nonzero "
            "3-vector, any length)."
        )
    return value


def _unit(v):
    return v / jnp.sqrt(jnp.sum(v**2))


def _perpendicular_pair(n):
    """An orthonormal pair `(u₁, u₂)` perpendicular to the unit `n`: Gram–Schmidt on the
    coordinate axis least aligned with `n` (a smooth choice near the given axis, so the
    derivative with respect to the axis exists)."""
    e = jnp.eye(3, dtype=n.dtype)[jnp.argmin(jnp.abs(n))]
    u1 = _unit(e - jnp.dot(e, n) * n)
    return u1, jnp.cross(n, u1)


def _rotation(g):
    return g[..., :3, :3]


def _position(g):
    return g[..., :3, 3]


class AbstractJoint(eqx.Module):
    """A holonomic joint between a parent pose and a child pose."""

    parent_point: eqx.AbstractVar[Float[Array, 3]]
    child_point: eqx.AbstractVar[Float[Array, 3]]

    @property
    @abc.abstractmethod
    def size(self) -> int:
        """The number of constraint equations."""

    @abc.abstractmethod
    def residual(self, parent, child, length):
        """`Φ(g_p, g_c)` in length units (`length`: the system's length scale)."""

    @abc.abstractmethod
    def jacobian(self, parent, child, length):
        """`(∂Φ/∂η_p, ∂Φ/∂η_c)`, each `(size, 6)`: the derivatives of `residual` along
        `g_p exp(ε η̂_p)` and `g_c exp(ε η̂_c)` at `ε = 0`, `η = (ω, v)`."""

    @abc.abstractmethod
    def describe(self) -> str:
        """A name for messages."""


def _ball_jacobian(parent, child, parent_point, child_point):
    """The ball joint's rows: `δ(x + R a) = R v + R (ω × a) = R v − R â ω` for each side,
    the parent's with `+`, the child's with `−`."""
    Rp, Rc = _rotation(parent), _rotation(child)
    # `R â` as `ω ↦ R (a × ω)`: the columns of `R â` are `R (a × e_j)`.
    Rp_a = Rp @ _hat(parent_point)
    Rc_a = Rc @ _hat(child_point)
    return (
        jnp.concatenate([-Rp_a, Rp], axis=1),
        jnp.concatenate([Rc_a, -Rc], axis=1),
    )


def _hat(v):
    zero = jnp.zeros((), v.dtype)
    return jnp.stack(
        [
            jnp.stack([zero, -v[2], v[1]]),
            jnp.stack([v[2], zero, -v[0]]),
            jnp.stack([-v[1], v[0], zero]),
        ]
    )


class BallJoint(AbstractJoint):
    """A ball (spherical) joint: a point of the parent and a point of the child coincide.

    **Arguments:**

    - `parent_point`: the joint point in the parent's frame, from its centre of mass (for
      a joint to the world, the point in the world frame: the pivot).
    - `child_point`: the joint point in the child's frame, from its centre of mass.
    """

    parent_point: Float[Array, 3]
    child_point: Float[Array, 3]

    def __init__(self, parent_point, child_point):
        self.parent_point = _vector("parent_point", parent_point)
        self.child_point = _vector("child_point", child_point)

    @property
    def size(self) -> int:
        return 3

    def residual(self, parent, child, length):
        """`Φ(g_p, g_c)`, `(3,)`: the parent's joint point minus the child's, in space."""
        del length
        a = _position(parent) + _rotation(parent) @ self.parent_point
        b = _position(child) + _rotation(child) @ self.child_point
        return a - b

    def jacobian(self, parent, child, length):
        del length
        return _ball_jacobian(parent, child, self.parent_point, self.child_point)

    def describe(self) -> str:
        return "ball joint"


class HingeJoint(AbstractJoint):
    """A hinge (revolute) joint: a ball joint that also keeps an axis of the child along an
    axis of the parent, leaving one rotation free.

    **Arguments:**

    - `parent_point`, `child_point`: a point on the hinge axis, in each body's frame from
      its centre of mass (for a joint to the world, the point in the world frame).
    - `axis`: the hinge axis in the child's frame (any nonzero length).
    - `parent_axis`: the hinge axis in the parent's frame (the world's for a joint to the
      world); default `axis` (the frames aligned, as the bodies are assembled).
    """

    parent_point: Float[Array, 3]
    child_point: Float[Array, 3]
    axis: Float[Array, 3]
    parent_axis: Float[Array, 3]

    def __init__(self, parent_point, child_point, axis, parent_axis=None):
        self.parent_point = _vector("parent_point", parent_point)
        self.child_point = _vector("child_point", child_point)
        self.axis = _axis("axis", axis)
        self.parent_axis = self.axis if parent_axis is None else _axis("parent_axis", parent_axis)

    @property
    def size(self) -> int:
        return 5

    def residual(self, parent, child, length):
        """`Φ(g_p, g_c)`, `(5,)`: the ball joint's three equations, then
        `ℓ (R_p u_α)·(R_c n_c)` for the two directions `u_α` perpendicular to the parent's
        axis."""
        ball = BallJoint(self.parent_point, self.child_point).residual(parent, child, length)
        n_child = _rotation(child) @ _unit(self.axis)
        u1, u2 = _perpendicular_pair(_unit(self.parent_axis))
        R = _rotation(parent)
        tilt = jnp.stack([jnp.dot(R @ u1, n_child), jnp.dot(R @ u2, n_child)])
        return jnp.concatenate([ball, length * tilt])

    def jacobian(self, parent, child, length):
        """The ball joint's rows, then the tilt's: with `w = R_pᵀ R_c n_c` and
        `q_α = R_cᵀ R_p u_α`, `δ[ℓ (R_p u_α)·(R_c n_c)] = ℓ ω_p·(u_α × w) + ℓ ω_c·(n_c × q_α)`
        (no translation)."""
        ball_p, ball_c = _ball_jacobian(parent, child, self.parent_point, self.child_point)
        n = _unit(self.axis)
        u = jnp.stack(_perpendicular_pair(_unit(self.parent_axis)))
        Rp, Rc = _rotation(parent), _rotation(child)
        w = Rp.T @ (Rc @ n)
        q = (Rc.T @ Rp @ u.T).T
        zeros = jnp.zeros((2, 3), Rp.dtype)
        tilt_p = jnp.concatenate([length * jnp.cross(u, w), zeros], axis=1)
        tilt_c = jnp.concatenate([length * jnp.cross(n, q), zeros], axis=1)
        return (
            jnp.concatenate([ball_p, tilt_p]),
            jnp.concatenate([ball_c, tilt_c]),
        )

    def describe(self) -> str:
        return "hinge joint"
