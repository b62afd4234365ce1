"""A group operation called eagerly is one compiled program, equal to the same operation
traced inside `jax.jit` (float64, to the bit: the same operations)."""

import functools

import jax
import numpy as np
import pytest

import lievi
from helpers import programs_compiled, random_rotation

RNG = np.random.default_rng(7)
B = 11  # a batch no other test uses: each first call here compiles
XI3 = RNG.normal(size=(B, 3)) * 0.7
XI6 = RNG.normal(size=(B, 6)) * 0.7
SO4 = lievi.SOn(4)
XI4 = RNG.normal(size=(B, 6)) * 0.7
R = np.stack([random_rotation(RNG, 3) for _ in range(B)])

CASES = [
    ("SO3.exp", lievi.SO3.exp, (XI3,)),
    ("SO3.log", lievi.SO3.log, (R,)),
    ("SO3.dexpinv", lievi.SO3.dexpinv, (XI3,)),
    ("SO3.compose", lievi.SO3.compose, (R, R)),
    ("SE3.exp", lievi.SE3.exp, (XI6,)),
    ("SE3.Ad", lievi.SE3.Ad, (np.asarray(jax.jit(lievi.SE3.exp)(XI6)),)),
    ("SOn(4).exp", SO4.exp, (XI4,)),
    ("SOn(4).log", SO4.log, (np.asarray(jax.jit(SO4.exp)(XI4 / 4)),)),
]


@pytest.mark.parametrize("name, op, args", CASES, ids=[c[0] for c in CASES])
def test_eager_operation_is_one_program(name, op, args):
    compiled = programs_compiled(lambda: op(*args))
    assert len(compiled) == 1, compiled
    assert programs_compiled(lambda: op(*args)) == []
    eager = np.asarray(op(*args))
    traced = np.asarray(jax.jit(op)(*args))
    np.testing.assert_array_equal(eager, traced)


@pytest.mark.parametrize("group", [lievi.SO3, lievi.SE3, SO4], ids=["SO3", "SE3", "SOn(4)"])
def test_traced_call_is_inline(group):
    """Under a transformation the operation is traced into the caller's program as the
    undecorated method is: the same jaxpr, no program of its own."""
    x = XI3 if group is lievi.SO3 else XI6
    plain = functools.partial(type(group).exp.__wrapped__, group)
    assert str(jax.make_jaxpr(group.exp)(x)) == str(jax.make_jaxpr(plain)(x))


def test_eager_shape_error_names_the_shape():
    with pytest.raises(ValueError, match="last axis 3"):
        lievi.SO3.hat(np.zeros((2, 4)))
