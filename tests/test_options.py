"""One set of run options: every run function takes the same keyword options with the same
defaults (`lievi/_options.py`), the spellings of earlier releases warn and give the same
run, implementation knobs live in `lievi.advanced`, and `diagnostics.energy` takes
`(system, g, m)` (its old order warns)."""

import inspect
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi._options import OPTIONS

RUNS = (
    lievi.simulate,
    lievi.simulate_batch,
    lievi.stream_batch,
    lievi.simulate_with_neighbor_list,
)
BODY = lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))
M0 = np.array([0.3, -0.2, 0.5])


@pytest.mark.parametrize("run", RUNS, ids=lambda run: run.__name__)
def test_every_run_function_takes_the_same_options_with_the_same_defaults(run):
    parameters = inspect.signature(run).parameters
    for name, default in OPTIONS.items():
        assert name in parameters, (run.__name__, name)
        assert parameters[name].kind is inspect.Parameter.KEYWORD_ONLY, (run.__name__, name)
        assert parameters[name].default == default, (run.__name__, name)
    assert OPTIONS["save"] == lievi.Save(g=True, m=True, stats=True, advected=False, every=1)
    # The spellings of earlier releases are read through `**deprecated`, not named.
    assert not {"save_every", "fast", "fixed_iterations", "unroll"} & set(parameters)
    assert any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())


def test_old_spellings_warn_and_give_the_same_run():
    run = dict(h=0.1, n_steps=4)
    new = lievi.simulate(BODY, lievi.RK4(), np.eye(3), M0, save=lievi.Save(every=2), **run)
    with pytest.warns(DeprecationWarning, match="save_every") as caught:
        old = lievi.simulate(BODY, lievi.RK4(), np.eye(3), M0, save_every=2, **run)
    assert caught[0].filename == __file__  # the warning points at the caller
    np.testing.assert_array_equal(old.m, new.m)
    np.testing.assert_array_equal(old.ts, new.ts)

    m0 = np.stack([M0, 2 * M0])
    tuned = lievi.advanced.Tuning(fast=False)
    new = lievi.simulate_batch(
        BODY, lievi.RK4(), np.eye(3), m0, save=lievi.Save(g=False, stats=False), tuning=tuned, **run
    )
    with pytest.warns(DeprecationWarning) as caught:
        old = lievi.simulate_batch(BODY, lievi.RK4(), np.eye(3), m0, save=("m",), fast=False, **run)
    messages = " ".join(str(w.message) for w in caught)
    assert "save=('m',)" in messages and "Tuning(fast=False)" in messages, messages
    assert old.g is None and new.g is None and old.stats.keys() == new.stats.keys()
    np.testing.assert_array_equal(old.m, new.m)


def test_option_errors_name_the_option():
    run = dict(h=0.1, n_steps=4)
    with pytest.raises(TypeError, match="save_evry"):
        lievi.simulate(BODY, lievi.DEP(), np.eye(3), M0, save_evry=2, **run)
    with pytest.raises(ValueError, match=r"`save.every` \(3\) must divide `n_steps` \(4\)"):
        lievi.simulate_batch(
            BODY, lievi.DEP(), np.eye(3), M0[None], save=lievi.Save(every=3), **run
        )
    with pytest.raises(ValueError, match="`Save.every` must be an integer"):
        lievi.Save(every=0)
    with pytest.raises(ValueError, match="`Tuning.unroll` must be an integer"):
        lievi.advanced.Tuning(unroll=0)
    with pytest.raises(ValueError, match="`tuning` must be a lievi.advanced.Tuning"):
        lievi.simulate(BODY, lievi.DEP(), np.eye(3), M0, tuning={"fast": False}, **run)
    with pytest.raises(ValueError, match="lievi.stream_batch does not take `checkpoint`"):
        lievi.stream_batch(
            BODY, lievi.DEP(), np.eye(3), M0[None], writer=None, checkpoint=True, **run
        )


def test_implementation_knobs_are_in_advanced():
    assert "has_fast_path" not in lievi.__all__ and "advanced" in lievi.__all__
    with pytest.warns(DeprecationWarning, match="lievi.advanced.has_fast_path"):
        old = lievi.has_fast_path
    assert old is lievi.advanced.has_fast_path
    assert lievi.advanced.has_fast_path(BODY, lievi.DEP())


def test_energy_takes_g_then_m_and_the_old_order_warns():
    top = lievi.heavy_top(jnp.array([1.0, 2.0, 3.0]), 1.0, jnp.array([0.0, 0.0, 0.5]))
    g = lievi.SO3.exp(jnp.array([[0.3, 0.0, 0.0], [0.0, 0.2, 0.1], [0.1, 0.1, 0.1]]))
    m = jnp.array([[0.3, -0.2, 0.5], [1.0, 0.0, 0.0], [0.0, 0.5, 0.5]])  # (3, 3), as one g
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the new order does not warn, even when a `(T, d)`
        new = lievi.diagnostics.energy(top, g, m)  # `m` has a group element's shape
        free = lievi.diagnostics.energy(BODY, None, m)
    assert new.shape == (3,) and np.all(np.isfinite(new))
    with pytest.warns(DeprecationWarning, match=r"energy\(system, g, m\)"):
        old = lievi.diagnostics.energy(top, m, g)
    np.testing.assert_array_equal(old, new)
    with pytest.warns(DeprecationWarning, match=r"energy\(system, g, m\)"):
        old_free = lievi.diagnostics.energy(BODY, m)
    np.testing.assert_array_equal(old_free, free)
    # The potential matters: `g` was really read as the attitude.
    assert np.all(new != lievi.diagnostics.energy(top, jnp.broadcast_to(jnp.eye(3), g.shape), m))
