"""Conversions between SO(3) matrices, quaternions (both storage orders), rotation vectors,
Euler angles, `scipy.spatial.transform.Rotation` and `jaxlie.SO3`.

Round trips to 1e-12 in float64 and 1e-6 in float32, at generic angles, near 0 and near π,
on batched inputs; the matrices agree with scipy's, which fixes the convention (body to
world, Hamilton quaternions) independently of lievi's own formulas.
"""

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
