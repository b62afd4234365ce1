"""`stream_batch`: a batch written chunk by chunk and segment by segment equals one
`simulate_batch` call; a stopped run resumes from its last finished segments."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi

B, N_STEPS, EVERY, SEGMENT, CHUNK = 10, 40, 4, 8, 4  # chunks of 4, 4, 2 bodies


def _problem():
    rng = np.random.default_rng(3)
    inertia = rng.uniform(0.5, 2.0, (B, 3))
    m0 = rng.normal(size=(B, 3))
    m0[7] *= 100.0  # h|Ω| past the step bound: body 7 fails at its first step
    g0 = np.asarray(lievi.SO3.exp(jnp.asarray(rng.normal(size=(B, 3)))))
    h = rng.uniform(0.05, 0.2, B)
    return jax.vmap(lievi.RigidBody)(jnp.asarray(inertia)), g0, m0, h


def _in_memory(fast=True):
    bodies, g0, m0, h = _problem()
    return lievi.simulate_batch(
        bodies, lievi.DEP(), g0, m0, h=h, n_steps=N_STEPS, save_every=EVERY, throw=False, fast=fast
    )


def _stream(directory, writer=None, **kwargs):
    bodies, g0, m0, h = _problem()
    kwargs = dict(dict(chunk_size=CHUNK, segment_steps=SEGMENT), **kwargs)
    lievi.stream_batch(
        bodies,
        lievi.DEP(),
        g0,
        m0,
        h=h,
        n_steps=N_STEPS,
        save_every=EVERY,
        writer=writer or lievi.NpyWriter(directory),
        **kwargs,
    )


def _read(directory):
    return {p.stem: np.load(p) for p in directory.glob("*.npy")}


def _assert_equal_to_in_memory(written, solution):
    assert written["g"].shape == solution.g.shape and written["m"].shape == solution.m.shape
    # Round-off, not bitwise: a chunk is vectorised with other shapes than the batch.
    np.testing.assert_allclose(written["g"], solution.g, rtol=0, atol=1e-14)
    np.testing.assert_allclose(written["m"], solution.m, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(written["result"], solution.result)
    np.testing.assert_array_equal(written["failed_step"], solution.stats["failed_step"])
    # A failed body's count: up to its failure (the generic path goes on counting the
    # iterations of the state it carries past the failure).
    ok = np.asarray(solution.result) == lievi.RESULTS.successful
    np.testing.assert_array_equal(
        written["total_newton_iterations"][ok], solution.stats["total_newton_iterations"][ok]
    )


@pytest.mark.parametrize("fast", [True, False])
def test_streamed_equals_in_memory(tmp_path, fast):
    solution = _in_memory(fast)
    assert int(solution.result[7]) == lievi.RESULTS.step_too_large  # the failing body ...
    assert np.all(np.isnan(np.asarray(solution.m[7, 1:])))  # ... is NaN after it
    assert np.all(np.asarray(solution.result)[np.arange(B) != 7] == lievi.RESULTS.successful)
    _stream(tmp_path, fast=fast)
    _assert_equal_to_in_memory(_read(tmp_path), solution)


class _Stop(Exception):
    pass


class _StopAfter(lievi.NpyWriter):
    """An `NpyWriter` that stops the run (as a killed process would) after `n` writes,
    and counts the segments it is given."""

    def __init__(self, directory, n):
        super().__init__(directory)
        self.n, self.written = n, []

    def write(self, chunk, rows, saves, values, state):
        if len(self.written) == self.n:
            raise _Stop
        self.written.append((chunk, state.steps_done))
        super().write(chunk, rows, saves, values, state)


def test_resume_after_a_stop(tmp_path):
    per_chunk = N_STEPS // SEGMENT  # 5 segments a chunk, 15 in all
    first = _StopAfter(tmp_path, 7)  # chunk 0 done, chunk 1 two segments in
    with pytest.raises(_Stop):
        _stream(tmp_path, first)
    assert first.written[-1] == (1, 2 * SEGMENT)
    second = _StopAfter(tmp_path, 100)
    _stream(tmp_path, second)
    # Only what was missing is computed: chunk 1 from its third segment, then chunk 2.
    assert second.written == [(1, k * SEGMENT) for k in range(3, per_chunk + 1)] + [
        (2, k * SEGMENT) for k in range(1, per_chunk + 1)
    ]
    _assert_equal_to_in_memory(_read(tmp_path), _in_memory())
    again = _StopAfter(tmp_path, 100)
    _stream(tmp_path, again)  # a finished run: nothing to do
    assert again.written == []


def test_save_m_only_and_progress(tmp_path, capsys):
    meter = lievi.TextProgressMeter(delay=0.0, prefix="stream")
    _stream(tmp_path, save=("m",), progress_meter=meter)
    jax.effects_barrier()
    out = capsys.readouterr().out
    values = [float(x) for x in re.findall(r"stream:\s+([\d.]+)%", out)]
    # One line, one update per finished segment (15), ending at 100%.
    assert out.count("\n") == 1 and len(values) == 16 and values[-1] == 100.0, out
    assert np.all(np.diff(values) > 0)
    written = _read(tmp_path)
    assert "g" not in written
    np.testing.assert_allclose(written["m"], _in_memory().m, rtol=0, atol=1e-13)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="`segment_steps`"):
        _stream(tmp_path, segment_steps=6)
    with pytest.raises(ValueError, match="`save`"):
        _stream(tmp_path, save=("m", "stats"))
    with pytest.raises(TypeError, match="`writer`"):
        _stream(tmp_path, writer=object())
    with pytest.raises(TypeError, match="forcing"):
        _stream(tmp_path, forcing=lievi.Control(jnp.zeros((N_STEPS, 3))))
    _stream(tmp_path / "run", save=("m",))
    with pytest.raises(ValueError, match="other settings"):
        _stream(tmp_path / "run", save=("g", "m"))
