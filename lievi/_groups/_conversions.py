"""Conversions between SO(3) matrices and the other rotation representations.

Convention (docs/theory/conventions.md): a rotation matrix `g` maps body coordinates to
world coordinates, `v_world = g v_body` — the active rotation that
`scipy.spatial.transform.Rotation.from_matrix` and `jaxlie.SO3.from_matrix` take. A unit
quaternion `q = w + x i + y j + z k` (Hamilton) stands for the same rotation as

    g = I + 2w q̂ + 2 q̂²,    q̂ the hat map of the vector part (x, y, z),

and the storage order is part of every name: `_wxyz` scalar-first (jaxlie), `_xyzw`
scalar-last (scipy). Every function is a pure `jax.numpy` function that accepts leading
batch axes and is differentiable, except the scipy adapters, which import scipy on
first use (`lievi.to_jaxlie` / `from_jaxlie` are in `_interop.py`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._so3 import SO3


def _check_last(name: str, x, shape: tuple[int, ...], what: str) -> None:
    if tuple(jnp.shape(x)[len(jnp.shape(x)) - len(shape) :]) != shape or jnp.ndim(x) < len(shape):
        raise ValueError(
            f"`{name}` must be {what} with trailing shape {shape}, got shape {jnp.shape(x)}."
        )


# ---- quaternions -------------------------------------------------------------------------


def quaternion_wxyz_to_matrix(q: Float[Array, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of a scalar-first quaternion `(w, x, y, z)`.

    **Arguments:**

    - `q`: quaternions, shape `(..., 4)`, scalar first. Normalised here, so any non-zero
      quaternion with finite components is accepted, however small or large its norm (it
      is scaled by its largest component before squaring); `q` and `−q` give the same
      matrix. The zero quaternion gives NaN.

    **Returns:** rotation matrices `g` (body to world), shape `(..., 3, 3)`.
    """
    _check_last("q", q, (4,), "a quaternion (w, x, y, z)")
    q = jnp.asarray(q)
    # Divide by the largest |component| before squaring: |q|² itself under- or overflows
    # in float32 for |q| ≲ 1e-19 or ≳ 1e19, the scaled one lies in [1, 4].
    scale = jnp.max(jnp.abs(q), axis=-1, keepdims=True)
    q = q / jnp.where(scale == 0, 1, scale)
    w, v = q[..., 0], q[..., 1:]
    s = 2 / jnp.sum(q * q, axis=-1)[..., None, None]
    V = SO3.hat(v)
    return jnp.eye(3, dtype=q.dtype) + s * (w[..., None, None] * V + V @ V)


def quaternion_xyzw_to_matrix(q: Float[Array, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of a scalar-last quaternion `(x, y, z, w)` (scipy's order).

    **Arguments:**

    - `q`: quaternions, shape `(..., 4)`, scalar last; normalised here.

    **Returns:** rotation matrices `g` (body to world), shape `(..., 3, 3)`.
    """
    _check_last("q", q, (4,), "a quaternion (x, y, z, w)")
    return quaternion_wxyz_to_matrix(xyzw_to_wxyz(q))


def matrix_to_quaternion_wxyz(g: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion `(w, x, y, z)` of a rotation matrix, with `w ≥ 0`.

    Shepperd's method: of the four expressions `4w² = 1 + tr g`, `4x² = 1 + 2g₁₁ − tr g`, …
    the largest is used to divide by, so the result is accurate to round-off for every
    rotation angle, including 0 and π.

    **Arguments:**

    - `g`: rotation matrices, shape `(..., 3, 3)`.

    **Returns:** unit quaternions, shape `(..., 4)`, scalar first, sign chosen so `w ≥ 0`.
    """
    _check_last("g", g, (3, 3), "a rotation matrix")
    g = jnp.asarray(g)
    trace = jnp.trace(g, axis1=-2, axis2=-1)
    d = jnp.diagonal(g, axis1=-2, axis2=-1)
    # 4·(w², x², y², z²)
    squares = jnp.stack(
        [
            1 + trace,
            1 + 2 * d[..., 0] - trace,
            1 + 2 * d[..., 1] - trace,
            1 + 2 * d[..., 2] - trace,
        ],
        axis=-1,
    )
    # Products 4·(w·x, w·y, w·z, x·y, x·z, y·z) from the off-diagonal entries.
    wx = g[..., 2, 1] - g[..., 1, 2]
    wy = g[..., 0, 2] - g[..., 2, 0]
    wz = g[..., 1, 0] - g[..., 0, 1]
    xy = g[..., 0, 1] + g[..., 1, 0]
    xz = g[..., 0, 2] + g[..., 2, 0]
    yz = g[..., 1, 2] + g[..., 2, 1]
    # Row c is 4·q_c·q; dividing by 2√(4q_c²) = 4|q_c| gives ±q.
    rows = jnp.stack(
        [
            jnp.stack([squares[..., 0], wx, wy, wz], axis=-1),
            jnp.stack([wx, squares[..., 1], xy, xz], axis=-1),
            jnp.stack([wy, xy, squares[..., 2], yz], axis=-1),
            jnp.stack([wz, xz, yz, squares[..., 3]], axis=-1),
        ],
        axis=-2,
    )
    c = jnp.argmax(squares, axis=-1)
    row = jnp.take_along_axis(rows, c[..., None, None], axis=-2)[..., 0, :]
    largest = jnp.take_along_axis(squares, c[..., None], axis=-1)
    q = row / (2 * jnp.sqrt(jnp.maximum(largest, jnp.finfo(g.dtype).tiny)))
    return jnp.where(q[..., :1] < 0, -q, q)


def matrix_to_quaternion_xyzw(g: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion `(x, y, z, w)` (scipy's order) of a rotation matrix, with `w ≥ 0`.

    **Arguments:**

    - `g`: rotation matrices, shape `(..., 3, 3)`.

    **Returns:** unit quaternions, shape `(..., 4)`, scalar last.
    """
    return wxyz_to_xyzw(matrix_to_quaternion_wxyz(g))


def wxyz_to_xyzw(q: Float[Array, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Reorder a scalar-first quaternion `(w, x, y, z)` to scalar-last `(x, y, z, w)`."""
    _check_last("q", q, (4,), "a quaternion (w, x, y, z)")
    return jnp.roll(jnp.asarray(q), -1, axis=-1)


def xyzw_to_wxyz(q: Float[Array, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Reorder a scalar-last quaternion `(x, y, z, w)` to scalar-first `(w, x, y, z)`."""
    _check_last("q", q, (4,), "a quaternion (x, y, z, w)")
    return jnp.roll(jnp.asarray(q), 1, axis=-1)


# ---- rotation vectors --------------------------------------------------------------------


def rotation_vector_to_matrix(v: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix `exp(v̂)` of a rotation vector (axis · angle, radians).

    The closed form of `lievi.SO3.exp`, NaN-free in values and gradients at `v = 0`.
    """
    _check_last("v", v, (3,), "a rotation vector")
    return SO3.exp(jnp.asarray(v))


def matrix_to_rotation_vector(g: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Rotation vector (axis · angle, `|v| ≤ π`) of a rotation matrix: `lievi.SO3.log`.

    Accurate up to and at the angle π (where the sign of the axis is a choice).
    """
    _check_last("g", g, (3, 3), "a rotation matrix")
    return SO3.log(jnp.asarray(g))


# ---- Euler angles ------------------------------------------------------------------------

_AXES = {"x": 0, "y": 1, "z": 2}


def _parse_sequence(seq: str) -> tuple[list[int], bool]:
    if (
        not isinstance(seq, str)
        or len(seq) != 3
        or not (seq.islower() or seq.isupper())
        or any(a not in _AXES for a in seq.lower())
        or seq[0].lower() == seq[1].lower()
        or seq[1].lower() == seq[2].lower()
    ):
        raise ValueError(
            f"`seq` must be three axes from 'xyz', consecutive axes different, all lowercase "
            f"(extrinsic: rotations about the fixed world axes) or all uppercase (intrinsic: "
            f"about the rotating body axes), e.g. 'xyz', 'ZYX', 'zxz'; got {seq!r}."
        )
    return [_AXES[a] for a in seq.lower()], seq.isupper()


def _axis_rotation(axis: int, angle):
    x = jnp.zeros(angle.shape + (3,), angle.dtype).at[..., axis].set(angle)
    return SO3.exp(x)


def euler_to_matrix(angles: Float[Array, "*batch 3"], seq: str) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of three Euler angles (radians), scipy's `from_euler` convention.

    **Arguments:**

    - `angles`: shape `(..., 3)`, the angle of the first, second and third rotation of `seq`.
    - `seq`: three axes, e.g. `"xyz"`. Lowercase: extrinsic (about the world axes,
      `g = R₃ R₂ R₁`); uppercase: intrinsic (about the body axes, `g = R₁ R₂ R₃`).

    **Returns:** rotation matrices, shape `(..., 3, 3)`.
    """
    axes, intrinsic = _parse_sequence(seq)
    _check_last("angles", angles, (3,), "three Euler angles")
    angles = jnp.asarray(angles)
    R = [_axis_rotation(a, angles[..., n]) for n, a in enumerate(axes)]
    return R[0] @ R[1] @ R[2] if intrinsic else R[2] @ R[1] @ R[0]


def matrix_to_euler(g: Float[Array, "*batch 3 3"], seq: str) -> Float[Array, "*batch 3"]:
    """Euler angles (radians) of rotation matrices, the inverse of `euler_to_matrix`.

    The direct quaternion method of Bernardes & Viollet, PLoS ONE 17 (2022) e0276302 (the
    one scipy uses), for every Tait–Bryan and proper Euler sequence. Ranges: first and
    third angle in `(−π, π]`; the middle one in `[−π/2, π/2]` (Tait–Bryan) or `[0, π]`
    (proper Euler). At gimbal lock (middle angle at an end of its range) only the sum or
    difference of the other two is defined; the last angle of `seq` is then set to 0, as
    scipy does (without its warning). Lock is detected within round-off only (middle angle
    within about 2·eps of the end; scipy uses 1e-7), so the angles reproduce the matrix to
    round-off at every distance from lock, in float32 too. Values and gradients are finite
    at lock too (e.g. at the identity for a proper Euler sequence).

    **Arguments:**

    - `g`: rotation matrices, shape `(..., 3, 3)`.
    - `seq`: as for `euler_to_matrix`.

    **Returns:** angles, shape `(..., 3)`, in the order of `seq`.
    """
    axes, intrinsic = _parse_sequence(seq)
    _check_last("g", g, (3, 3), "a rotation matrix")
    if intrinsic:  # intrinsic (i, j, k) = extrinsic (k, j, i) with the angles reversed
        axes = axes[::-1]
    i, j, k = axes
    proper = i == k
    if proper:
        k = 3 - i - j
    sign = float((i - j) * (j - k) * (k - i) // 2)  # +1 for a cyclic (i, j, k), −1 otherwise
    q = matrix_to_quaternion_wxyz(g)
    w, qi, qj, qk = q[..., 0], q[..., 1 + i], q[..., 1 + j], q[..., 1 + k] * sign
    if proper:
        a, b, c, d = w, qi, qj, qk
    else:
        a, b, c, d = w - qj, qi + qk, qj + w, qk - qi
    # (a, b) and (c, d) in polar form: radii cos(β/2), sin(β/2) (times √2 for Tait–Bryan),
    # angles the half sum and half difference of the outer angles. Each is converted to
    # relative accuracy, so the angles reproduce the matrix to round-off however close to
    # gimbal lock it is (an ill-conditioned outer angle is compensated by a small radius).
    r, s = _hypot(a, b), _hypot(c, d)
    middle = 2 * jnp.arctan2(s, r)
    # Gimbal lock: a radius below round-off of the other. Then the half difference
    # (middle 0) or half sum (middle π) is undefined and the last angle of `seq` is set to
    # 0. Setting it changes the matrix by about 4·eps, so the threshold is eps itself: a
    # larger one (as scipy's 1e-7) would not reproduce float32 matrices near lock.
    eps = jnp.finfo(q.dtype).eps
    lock_zero = s <= eps * r
    lock_pi = ~lock_zero & (r <= eps * s)
    lock = lock_zero | lock_pi
    # Both branches of a `where` are differentiated: the undefined angle is computed from a
    # safe input where it is not used, so gradients stay finite at lock (e.g. the identity
    # for a proper Euler sequence).
    half_sum = _atan2_unless(b, a, lock_pi)
    half_difference = _atan2_unless(d, c, lock_zero)
    # At lock only first + third (middle 0) or third − first (middle π) is defined; the
    # angle that comes last in `seq` is set to 0.
    locked = jnp.where(lock_zero, 2 * half_sum, 2 * half_difference)
    if intrinsic:  # `seq`'s last angle is the extrinsic first one
        first = jnp.where(lock, 0.0, half_sum - half_difference)
        third = jnp.where(lock, locked, half_sum + half_difference)
    else:
        first = jnp.where(lock, jnp.where(lock_zero, locked, -locked), half_sum - half_difference)
        third = jnp.where(lock, 0.0, half_sum + half_difference)
    if not proper:
        third = sign * third
        middle = middle - jnp.pi / 2
    first, third = _wrap(first), _wrap(third)
    angles = jnp.stack([first, middle, third], axis=-1)
    return angles[..., ::-1] if intrinsic else angles


def _hypot(x, y):
    """`hypot(x, y)` with gradient 0 (not NaN) at `x = y = 0`."""
    zero = (x == 0) & (y == 0)
    return jnp.where(zero, 0, jnp.hypot(jnp.where(zero, 1, x), y))


def _atan2_unless(y, x, undefined):
    """`atan2(y, x)`, with a safe input (value 0, finite gradient) where `undefined`."""
    return jnp.arctan2(jnp.where(undefined, 0, y), jnp.where(undefined, 1, x))


def _wrap(angle):
    """Into `(−π, π]`."""
    return jnp.where(
        angle <= -jnp.pi, angle + 2 * jnp.pi, jnp.where(angle > jnp.pi, angle - 2 * jnp.pi, angle)
    )


# ---- other libraries ---------------------------------------------------------------------


def to_scipy_rotation(g: Float[Array, "*batch 3 3"]):
    """A `scipy.spatial.transform.Rotation` holding the rotations `g` (body to world).

    Built from the quaternions (`Rotation.from_quat`, scalar-last), so no projection onto
    SO(3) alters the matrices. Leading batch axes of `g` are flattened into scipy's single
    batch axis. Needs scipy (a lievi dependency).
    """
    from scipy.spatial.transform import Rotation

    _check_last("g", g, (3, 3), "a rotation matrix")
    q = matrix_to_quaternion_xyzw(jnp.asarray(g))
    import numpy as np

    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q if q.ndim <= 2 else q.reshape(-1, 4))


def from_scipy_rotation(rotation, dtype=None) -> Float[Array, "*batch 3 3"]:
    """Rotation matrices `g` (body to world) of a `scipy.spatial.transform.Rotation`.

    **Arguments:**

    - `rotation`: a single or stacked `Rotation`.
    - `dtype`: of the result; by default JAX's default float (float64 with x64 enabled).

    **Returns:** `(3, 3)` or `(N, 3, 3)`, from the quaternions so as exact as they are.
    """
    return quaternion_xyzw_to_matrix(jnp.asarray(rotation.as_quat(), dtype=dtype))
