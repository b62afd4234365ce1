"""Conversions between SO(3) matrices, quaternions (both storage orders), rotation vectors,
Euler angles, `scipy.spatial.transform.Rotation` and `jaxlie.SO3`.

Round trips to 1e-12 in float64 and 1e-6 in float32, at generic angles, near 0 and near π,
on batched inputs; the matrices agree with scipy's, which fixes the convention (body to
world, Hamilton quaternions) independently of lievi's own formulas.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import lievi

TOL = {jnp.float64: 1e-12, jnp.float32: 1e-6}

# Compiled once per shape (eager dispatch of every primitive would dominate the test time).
_SEQ = {"matrix_to_euler", "euler_to_matrix"}
L = type(
    "L",
    (),
    {
        name: staticmethod(
            jax.jit(getattr(lievi, name), static_argnums=(1,) if name in _SEQ else ())
        )
        for name in [
            "rotation_vector_to_matrix",
            "matrix_to_rotation_vector",
            "matrix_to_quaternion_wxyz",
            "matrix_to_quaternion_xyzw",
            "quaternion_wxyz_to_matrix",
            "quaternion_xyzw_to_matrix",
            "wxyz_to_xyzw",
            "xyzw_to_wxyz",
            *_SEQ,
        ]
    },
)


def rotation_vectors(rng, n=64):
    """Rotation vectors with angles generic, tiny, zero and up to π."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [
            rng.uniform(0, np.pi, n - 16),
            [0.0, 1e-12, 1e-8, 1e-4, 1e-2, 0.5, 1.0, 2.0],
            np.pi - np.array([1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 1e-14, 0.0]),
        ]
    )
    return axes * angles[:, None]


@pytest.fixture
def vectors():
    return rotation_vectors(np.random.default_rng(0))


def test_matrices_agree_with_scipy(vectors):
    ours = L.rotation_vector_to_matrix(jnp.asarray(vectors))
    theirs = Rotation.from_rotvec(vectors).as_matrix()
    np.testing.assert_allclose(ours, theirs, atol=1e-14)
    # Quaternions: the same rotation as scipy, scipy's storage order for `_xyzw`.
    q = L.matrix_to_quaternion_xyzw(ours)
    np.testing.assert_allclose(L.quaternion_xyzw_to_matrix(q), theirs, atol=1e-14)
    q_scipy = Rotation.from_matrix(theirs).as_quat()
    same_sign = np.sign(np.sum(q * q_scipy, axis=1))[:, None]
    np.testing.assert_allclose(q, same_sign * q_scipy, atol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_quaternion_round_trips(vectors, dtype):
    g = L.rotation_vector_to_matrix(jnp.asarray(vectors, dtype))
    for to_q, from_q in [
        (lievi.matrix_to_quaternion_wxyz, lievi.quaternion_wxyz_to_matrix),
        (lievi.matrix_to_quaternion_xyzw, lievi.quaternion_xyzw_to_matrix),
    ]:
        q = to_q(g)
        assert q.dtype == dtype
        np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1, atol=TOL[dtype])
        np.testing.assert_allclose(from_q(q), g, atol=TOL[dtype])
        np.testing.assert_allclose(to_q(from_q(q)), q, atol=TOL[dtype])
    wxyz = L.matrix_to_quaternion_wxyz(g)
    assert jnp.all(wxyz[..., 0] >= 0)
    np.testing.assert_array_equal(L.wxyz_to_xyzw(wxyz), L.matrix_to_quaternion_xyzw(g))
    np.testing.assert_array_equal(L.xyzw_to_wxyz(L.wxyz_to_xyzw(wxyz)), wxyz)
    # q and −q are one rotation; non-unit quaternions are normalised.
    np.testing.assert_allclose(L.quaternion_wxyz_to_matrix(-3 * wxyz), g, atol=TOL[dtype])


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_rotation_vector_round_trips(vectors, dtype):
    v = jnp.asarray(vectors, dtype)
    g = L.rotation_vector_to_matrix(v)
    back = L.matrix_to_rotation_vector(g)
    # At exactly π, v and −v are the same rotation: compare matrices there.
    np.testing.assert_allclose(L.rotation_vector_to_matrix(back), g, atol=TOL[dtype])
    generic = np.linalg.norm(vectors, axis=1) < np.pi - 1e-3
    np.testing.assert_allclose(back[generic], v[generic], atol=TOL[dtype])


def test_batched_shapes():
    rng = np.random.default_rng(1)
    v = jnp.asarray(rotation_vectors(rng, 24).reshape(2, 3, 4, 3))
    g = L.rotation_vector_to_matrix(v)
    assert g.shape == (2, 3, 4, 3, 3)
    assert L.matrix_to_quaternion_wxyz(g).shape == (2, 3, 4, 4)
    assert L.matrix_to_euler(g, "ZYX").shape == (2, 3, 4, 3)
    single = L.matrix_to_quaternion_wxyz(g[1, 2, 3])
    np.testing.assert_array_equal(L.matrix_to_quaternion_wxyz(g)[1, 2, 3], single)
    # jit and vmap give the same numbers.
    np.testing.assert_allclose(
        jax.jit(jax.vmap(lievi.matrix_to_quaternion_xyzw))(g.reshape(-1, 3, 3)),
        L.matrix_to_quaternion_xyzw(g).reshape(-1, 4),
        atol=1e-15,
    )


# Tait–Bryan and proper Euler, extrinsic and intrinsic, cyclic and anticyclic.
SEQUENCES = ["xyz", "zyx", "XYZ", "ZYX", "zxz", "XZX"]


# The sample's identity and tiny rotations are at gimbal lock for the proper sequences
# (middle angle 0): lievi's angles must still reproduce the matrix there; scipy warns, and
# those rotations are excluded from the comparison of angles below.
@pytest.mark.filterwarnings("ignore:Gimbal lock detected:UserWarning")
@pytest.mark.parametrize("seq", SEQUENCES)
def test_euler_angles_agree_with_scipy(vectors, seq):
    g = L.rotation_vector_to_matrix(jnp.asarray(vectors))
    angles = L.matrix_to_euler(g, seq)
    np.testing.assert_allclose(L.euler_to_matrix(angles, seq), g, atol=1e-12)
    np.testing.assert_allclose(
        L.euler_to_matrix(angles, seq),
        Rotation.from_euler(seq, np.asarray(angles)).as_matrix(),
        atol=1e-12,
    )
    # Away from gimbal lock the angles are unique in their ranges: equal to scipy's.
    theirs = Rotation.from_matrix(np.asarray(g)).as_euler(seq)
    middle = np.asarray(angles[:, 1])
    proper = seq[0].lower() == seq[2].lower()
    far = np.abs(np.sin(middle) if proper else np.cos(middle)) > 1e-3
    far &= np.abs(np.abs(theirs[:, 0]) - np.pi) > 1e-6
    far &= np.abs(np.abs(theirs[:, 2]) - np.pi) > 1e-6
    np.testing.assert_allclose(angles[far], theirs[far], atol=1e-10)


@pytest.mark.parametrize(
    "seq, dtype",
    [("xyz", jnp.float64), ("ZYX", jnp.float32), ("zxz", jnp.float64), ("XYX", jnp.float32)],
)
def test_euler_gimbal_lock_round_trip(seq, dtype):
    proper = seq[0].lower() == seq[2].lower()
    lock = [0.0, np.pi] if proper else [np.pi / 2, -np.pi / 2]
    angles = jnp.asarray([[0.3, m, -1.1] for m in lock] + [[0.7, 0.4, 2.5]], dtype)
    g = L.euler_to_matrix(angles, seq)
    np.testing.assert_allclose(
        L.euler_to_matrix(L.matrix_to_euler(g, seq), seq), g, atol=TOL[dtype] * 10
    )


def test_scipy_round_trip(vectors):
    g = L.rotation_vector_to_matrix(jnp.asarray(vectors))
    r = lievi.to_scipy_rotation(g)
    assert isinstance(r, Rotation) and len(r) == len(vectors)
    np.testing.assert_allclose(r.as_matrix(), g, atol=1e-12)
    np.testing.assert_allclose(lievi.from_scipy_rotation(r), g, atol=1e-12)
    one = lievi.from_scipy_rotation(lievi.to_scipy_rotation(g[3]))
    assert one.shape == (3, 3)
    np.testing.assert_allclose(one, g[3], atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_jaxlie_round_trip(vectors, dtype):
    jaxlie = pytest.importorskip("jaxlie")
    g = L.rotation_vector_to_matrix(jnp.asarray(vectors, dtype))
    R = lievi.to_jaxlie(g)
    assert isinstance(R, jaxlie.SO3)
    np.testing.assert_allclose(R.as_matrix(), g, atol=TOL[dtype])
    np.testing.assert_allclose(lievi.from_jaxlie(R), g, atol=TOL[dtype])
    # The same rotation acts the same way on a vector (body to world).
    p = jnp.asarray([0.3, -1.2, 0.5], dtype)
    np.testing.assert_allclose(jax.vmap(lambda r: r @ p)(R), g @ p, atol=10 * TOL[dtype])
    # jaxlie's own exp agrees with lievi's on the rotation vectors.
    np.testing.assert_allclose(
        jax.vmap(lambda v: jaxlie.SO3.exp(v).as_matrix())(jnp.asarray(vectors, dtype)),
        g,
        atol=10 * TOL[dtype],
    )


def test_gradients_are_finite_at_zero_and_pi():
    def loss(v):
        q = lievi.matrix_to_quaternion_wxyz(lievi.rotation_vector_to_matrix(v))
        return jnp.sum(q * jnp.array([1.0, 2.0, 3.0, 4.0]))

    v = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-9], [1e-9, 0.0, 0.0], [0.3, -0.2, 1.0]])
    assert jnp.all(jnp.isfinite(jax.jit(jax.vmap(jax.grad(loss)))(v)))


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="`q`"):
        lievi.quaternion_wxyz_to_matrix(jnp.zeros(3))
    with pytest.raises(ValueError, match="`g`"):
        lievi.matrix_to_quaternion_xyzw(jnp.zeros((3, 4)))
    with pytest.raises(ValueError, match="`seq`"):
        lievi.euler_to_matrix(jnp.zeros(3), "xxy")
    with pytest.raises(ValueError, match="`seq`"):
        lievi.matrix_to_euler(jnp.eye(3), "xYz")


_AXIS = {"x": 0, "y": 1, "z": 2}
# Every proper Euler sequence, extrinsic and intrinsic, and some Tait–Bryan ones.
PROPER = [a + b + a for a in "xyz" for b in "xyz" if a != b]
PROPER += [s.upper() for s in PROPER]
LOCK_SEQUENCES = (*PROPER, "xyz", "ZYX", "yxz", "XZY")
# Angles about one axis: the identity, tiny, generic, up to the half-turn.
ALONG = [0.0, 1e-3, 0.7, np.pi / 2, np.pi - 1e-3, np.pi]
WEIGHTS = [1.0, 2.0, 3.0]


def lock_points():
    """Rotation vectors: `t·e_a` for every axis `a` and `t` in `ALONG` (gimbal lock of a
    proper sequence whose first axis is `a`; middle angle 0, or π for `t = π` about its
    middle axis), ±π/2 about every axis (Tait–Bryan lock), and for every sequence a lock
    with both outer angles nonzero."""
    about_axes = [t * e for e in np.eye(3) for t in ALONG]
    minus = [-np.pi / 2 * e for e in np.eye(3)]
    generic = []
    for seq in LOCK_SEQUENCES:
        proper = seq[0].lower() == seq[2].lower()
        for middle in [0.0, np.pi] if proper else [np.pi / 2, -np.pi / 2]:
            generic.append(Rotation.from_euler(seq, [0.4, middle, -1.3]).as_rotvec())
    return np.asarray(about_axes + minus + generic)


@functools.partial(jax.jit, static_argnums=(1,))
def angles_and_gradients(r, sequences):
    """Per sequence: the angles of `exp(r)` and the gradient of a weighted sum of them
    with respect to `r` (one compilation for all sequences)."""
    out = {}
    for seq in sequences:

        def loss(r, seq=seq):
            angles = lievi.matrix_to_euler(lievi.SO3.exp(r), seq)
            return jnp.sum(jnp.asarray(WEIGHTS, r.dtype) * angles), angles

        grads, angles = jax.vmap(jax.grad(loss, has_aux=True))(r)
        out[seq] = angles, grads
    return out


@pytest.mark.extended  # 16–21 s each
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_euler_gradients_finite_at_gimbal_lock(dtype):
    """At the identity (the usual initial attitude) and at every rotation about the first
    axis (half-turns included) a proper Euler sequence is at gimbal lock (middle angle 0);
    π about the middle axis is the other lock (middle π), ±π/2 about the middle axis the
    Tait–Bryan lock. Values reproduce the matrix (10·TOL); gradients of a loss on the
    angles through `g = SO3.exp(r)` are finite, and along the lock (rotations by `t` about
    the first axis, angles exactly `(t, 0, 0)`) they are the derivative along that curve:
    the first angle's weight (to 10·eps)."""
    r = jnp.asarray(lock_points(), dtype)
    g = L.rotation_vector_to_matrix(r)
    eps = float(jnp.finfo(dtype).eps)
    for seq, (angles, grads) in angles_and_gradients(r, LOCK_SEQUENCES).items():
        assert bool(jnp.all(jnp.isfinite(angles))), seq
        back = Rotation.from_euler(seq, np.asarray(angles, np.float64)).as_matrix()
        np.testing.assert_allclose(back, g, atol=10 * TOL[dtype], err_msg=seq)
        assert bool(jnp.all(jnp.isfinite(grads))), (seq, grads)
        if seq[0].lower() == seq[2].lower():
            first = _AXIS[seq[0].lower()]
            rows = slice(len(ALONG) * first, len(ALONG) * (first + 1))
            np.testing.assert_array_equal(angles[rows, 1:], 0, err_msg=seq)
            np.testing.assert_allclose(np.abs(angles[rows, 0]), ALONG, atol=10 * eps)
            np.testing.assert_allclose(grads[rows, first], WEIGHTS[0], atol=10 * eps)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_quaternions_of_any_norm(dtype):
    """Any non-zero quaternion is normalised, however small or large: in float32 |q|²
    underflows for |q| ≲ 1e-19 and overflows for |q| ≳ 1e19, so the scaled quaternion is
    squared instead. Scales down to just above the smallest normal number; the matrix
    equals the unit quaternion's to TOL (1e-6 in float32) and is a rotation (gᵀg = I to
    TOL)."""
    q = jnp.asarray(np.random.default_rng(3).normal(size=(8, 4)), dtype)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    exponent = np.log10(float(jnp.finfo(dtype).max))
    scales = 10.0 ** np.concatenate(
        [np.linspace(-exponent + 3, exponent - 1, 9), [-20, -19, -18, 18, 19, 20]]
    )
    g = L.quaternion_wxyz_to_matrix(q)
    eye = np.eye(3)
    for scale in np.asarray(scales, dtype):
        for to_matrix, scaled in [
            (L.quaternion_wxyz_to_matrix, scale * q),
            (L.quaternion_xyzw_to_matrix, scale * L.wxyz_to_xyzw(q)),
        ]:
            normal = jnp.isfinite(scaled) & (jnp.abs(scaled) >= jnp.finfo(dtype).tiny)
            assert bool(jnp.all(normal)), scale
            ours = to_matrix(scaled)
            np.testing.assert_allclose(ours, g, atol=TOL[dtype], err_msg=f"scale {scale}")
            gram = jnp.swapaxes(ours, -1, -2) @ ours
            np.testing.assert_allclose(gram, np.broadcast_to(eye, gram.shape), atol=TOL[dtype])


def near_lock_angles(seq, offsets, rng, per_offset=4):
    """Angles whose middle is `offset` from each gimbal lock of `seq`, inside the middle
    angle's range, outer angles uniform in (−π, π)."""
    proper = seq[0].lower() == seq[2].lower()
    locks = [0.0, np.pi] if proper else [np.pi / 2, -np.pi / 2]
    low, high = (0, np.pi) if proper else (-np.pi / 2, np.pi / 2)
    middles = [
        lock + side * offset
        for lock in locks
        for offset in offsets
        for side in (1, -1)
        if low <= lock + side * offset <= high
    ]
    middles = np.repeat(middles, per_offset)
    outer = rng.uniform(-np.pi, np.pi, size=(len(middles), 2))
    return np.stack([outer[:, 0], middles, outer[:, 1]], axis=-1)


# Near gimbal lock only the matrix is well conditioned: the outer angles individually
# are not (their error grows like eps / offset), so the round trip compares matrices.
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("seq", ["xyz", "ZYX", "zxz", "XYX"])
def test_euler_round_trip_near_gimbal_lock(seq, dtype):
    """Middle angles 1e-7 … 1e-3 rad from lock (through the lock threshold, which is
    about 2·eps): `euler_to_matrix(matrix_to_euler(g))` reproduces `g` to TOL (1e-12 in
    float64, 1e-6 in float32 — the accuracy the docs promise), and the middle angle is
    recovered to TOL (it is well conditioned)."""
    angles = near_lock_angles(seq, np.geomspace(1e-7, 1e-3, 13), np.random.default_rng(4))
    g = L.euler_to_matrix(jnp.asarray(angles), seq).astype(dtype)
    back = L.matrix_to_euler(g, seq)
    np.testing.assert_allclose(L.euler_to_matrix(back, seq), g, atol=TOL[dtype])
    np.testing.assert_allclose(back[:, 1], angles[:, 1], atol=TOL[dtype])
