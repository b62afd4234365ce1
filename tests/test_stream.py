"""`stream_batch`: a batch written chunk by chunk and segment by segment equals one
`simulate_batch` call; a stopped run resumes from its last finished segments."""

import errno
import json
import os
import re
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi

B, N_STEPS, EVERY, SEGMENT, CHUNK = 10, 40, 4, 8, 4  # chunks of 4, 4, 2 bodies
M_ONLY = lievi.Save(g=False, every=EVERY)  # `m` alone, every `EVERY` steps


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
        bodies,
        lievi.DEP(),
        g0,
        m0,
        h=h,
        n_steps=N_STEPS,
        save=lievi.Save(every=EVERY),
        tuning=lievi.advanced.Tuning(fast=fast),
        throw=False,
    )


def _stream(directory, writer=None, **kwargs):
    bodies, g0, m0, h = _problem()
    defaults = dict(
        chunk_size=CHUNK, segment_steps=SEGMENT, throw=False, save=lievi.Save(every=EVERY)
    )
    kwargs = dict(defaults, **kwargs)
    lievi.stream_batch(
        bodies,
        lievi.DEP(),
        g0,
        m0,
        h=h,
        n_steps=N_STEPS,
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


@pytest.mark.parametrize(
    "fast",
    [pytest.param(True, marks=pytest.mark.extended), False],  # True: 14 s
)
def test_streamed_equals_in_memory(tmp_path, fast):
    solution = _in_memory(fast)
    assert int(solution.result[7]) == lievi.RESULTS.step_too_large  # the failing body ...
    assert np.all(np.isnan(np.asarray(solution.m[7, 1:])))  # ... is NaN after it
    assert np.all(np.asarray(solution.result)[np.arange(B) != 7] == lievi.RESULTS.successful)
    _stream(tmp_path, tuning=lievi.advanced.Tuning(fast=fast))
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


@pytest.mark.extended  # 15 s
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


@pytest.mark.extended  # 14 s
def test_save_m_only_and_progress(tmp_path, capsys):
    meter = lievi.TextProgressMeter(delay=0.0, prefix="stream")
    _stream(tmp_path, save=M_ONLY, progress_meter=meter)
    jax.effects_barrier()
    out = capsys.readouterr().out
    values = [float(x) for x in re.findall(r"stream:\s+([\d.]+)%", out)]
    # One line, one update per finished segment (15), ending at 100%.
    assert out.count("\n") == 1 and len(values) == 16 and values[-1] == 100.0, out
    assert np.all(np.diff(values) > 0)
    written = _read(tmp_path)
    assert "g" not in written
    np.testing.assert_allclose(written["m"], _in_memory().m, rtol=0, atol=1e-13)


@pytest.mark.extended  # 19 s
def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="`segment_steps`"):
        _stream(tmp_path, segment_steps=6)
    with pytest.raises(ValueError, match="`save`"):
        _stream(tmp_path, save=lievi.Save(g=False, m=False))
    with pytest.raises(TypeError, match="`writer`"):
        _stream(tmp_path, writer=object())
    with pytest.raises(ValueError, match="forcing"):
        _stream(tmp_path, forcing=lievi.Control(jnp.zeros((N_STEPS, 3))))
    _stream(tmp_path / "run", save=M_ONLY)
    with pytest.raises(ValueError, match="differs in `fields`"):
        _stream(tmp_path / "run", save=lievi.Save(every=EVERY))


# ---- data integrity: small runs of one shared body, one compiled program for all ----------

SMALL = dict(
    h=0.05, n_steps=8, save=lievi.Save(every=2), segment_steps=4, chunk_size=2
)  # 2 × 2 pieces
NOT_RUN = lievi.RESULTS.not_run
SMALL_M_ONLY = lievi.Save(g=False, every=2)  # `m` alone, at `SMALL`'s saves


def _small_m0():
    return np.random.default_rng(5).normal(size=(4, 3))


def _small(directory, writer=None, **changes):
    """A small streamed run (4 bodies in 2 chunks of 2 segments), `changes` to its
    arguments applied."""
    arguments = dict(
        SMALL,
        system=lievi.RigidBody(jnp.array([1.0, 2.0, 3.0])),
        integrator=lievi.LiePoissonSplitting(),
        g0=np.eye(3),
        m0=_small_m0(),
    )
    arguments.update(changes)
    system, integrator = arguments.pop("system"), arguments.pop("integrator")
    g0, m0 = arguments.pop("g0"), arguments.pop("m0")
    writer = writer or lievi.NpyWriter(directory)
    lievi.stream_batch(system, integrator, g0, m0, writer=writer, **arguments)


def test_other_physics_on_an_existing_directory_is_refused(tmp_path):
    """Half-finished or finished, a directory resumes only the run that wrote it: other
    physics, initial states or step sizes are a `ValueError` naming what differs (and
    write nothing); the same arguments resume it, or on a finished one return at once."""
    with pytest.raises(_Stop):
        _small(tmp_path, _StopAfter(tmp_path, 1))  # chunk 0, its first segment
    with pytest.raises(ValueError, match="differs in `m0`"):
        _small(tmp_path, _StopAfter(tmp_path, 0), m0=2 * _small_m0())
    _small(tmp_path)  # resumed: the same arguments
    finished = _read(tmp_path)
    other_body = lievi.RigidBody(jnp.array([1.0, 2.0, 4.0]))
    for change, field in [
        (dict(h=0.1), "h"),
        (dict(integrator=lievi.DEP()), "integrator"),
        (dict(system=other_body), "system"),
        (dict(g0=np.broadcast_to(np.eye(3), (4, 3, 3))), "g0"),
        (dict(n_steps=16), "n_steps"),
        (dict(tuning=lievi.advanced.Tuning(fast=False)), "options"),
    ]:
        with pytest.raises(ValueError, match=f"differs in .*`{field}`"):
            _small(tmp_path, _StopAfter(tmp_path, 0), **change)
    again = _StopAfter(tmp_path, 0)  # raises if asked to write anything
    _small(tmp_path, again)
    for name, values in _read(tmp_path).items():
        np.testing.assert_array_equal(values, finished[name])


def test_a_batch_of_systems_of_the_wrong_size_is_refused_before_any_file(tmp_path):
    """An explicit `system_axis=0` whose systems do not match the bodies: a `ValueError`
    naming `system_axis` before the writer creates anything."""
    systems = jax.vmap(lievi.RigidBody)(jnp.array([[1.0, 2.0, 3.0]] * 3))  # 3, not 4
    with pytest.raises(ValueError, match="`system_axis=0`.*leading axis 4"):
        _small(tmp_path / "run", system=systems, system_axis=0)
    assert not (tmp_path / "run").exists()


def test_run_record_sees_static_fields_not_addresses():
    """A pytree's digest covers its static fields (a chart, a function held by the system,
    by its name) but not the memory addresses in their `repr`, which another process (a
    resumed run) would not share."""
    from lievi._stream_record import tree_digest

    def coupling():
        def potential(g):  # a new function object at each call, at a new address
            return jnp.sum(g[0] * g[1])

        return potential

    def rotors(potential):
        return lievi.RigidRotors(jnp.ones((2, 3)), potential)

    assert tree_digest(lievi.DEP()) == tree_digest(lievi.DEP())
    assert tree_digest(lievi.DEP()) != tree_digest(lievi.DEP(chart="cayley"))
    assert tree_digest(rotors(coupling())) == tree_digest(rotors(coupling()))
    assert tree_digest(rotors(coupling())) != tree_digest(rotors(jnp.sum))


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _path_of(fd):
    return os.readlink(f"/proc/self/fd/{fd}")


def _size_limit(limit, name, real_pwrite=os.pwrite):
    """`os.pwrite` as under a file-size limit of `limit` bytes on the file `name` (as
    `RLIMIT_FSIZE`, or a full disk, would have it): a write across the limit stores the
    bytes below it and returns their count; one at or past it fails with `EFBIG`."""

    def pwrite(fd, data, position):
        if not _path_of(fd).endswith(name) or position + len(data) <= limit:
            return real_pwrite(fd, data, position)
        if position >= limit:
            raise OSError(errno.EFBIG, "File too large")
        return real_pwrite(fd, bytes(data)[: limit - position], position)

    return pwrite


def test_short_write_raises_and_the_segment_is_redone(tmp_path, monkeypatch):
    """A write the disk takes only in part (the last body's saves in the last segment, so
    no later write would fail) is an `OSError`; the segment is not recorded as done, and
    a resume redoes it: the output then equals that of an uninterrupted run."""
    _small(tmp_path / "whole")
    run = tmp_path / "run"
    with pytest.raises(_Stop):
        _small(run, _StopAfter(run, 3), save=SMALL_M_ONLY)  # all but chunk 1's second segment
    header = np.load(run / "m.npy", mmap_mode="r").offset
    per_row, per_save = 5 * 3 * 8, 3 * 8  # 5 saves of (3,) float64
    limit = header + 3 * per_row + 3 * per_save + per_save // 2  # within body 3's save 3
    monkeypatch.setattr(os, "pwrite", _size_limit(limit, "m.npy"))
    with pytest.raises(OSError, match="m.npy"):
        _small(run, save=SMALL_M_ONLY)
    monkeypatch.undo()
    assert lievi.NpyWriter(run).resume_state(1).steps_done == 4  # the first segment only
    np.testing.assert_array_equal(np.load(run / "result.npy")[2:], NOT_RUN)
    assert not (run / "complete.json").exists()
    _small(run, save=SMALL_M_ONLY)
    np.testing.assert_array_equal(np.load(run / "m.npy"), np.load(tmp_path / "whole" / "m.npy"))
    np.testing.assert_array_equal(np.load(run / "result.npy"), lievi.RESULTS.successful)


def test_data_on_disk_before_the_state_says_done(tmp_path, monkeypatch):
    """Each segment's data files are flushed to the disk (`fsync`) before the state file
    that records the segment as done replaces the old one."""
    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append(_path_of(fd)), real_fsync(fd)))
    monkeypatch.setattr(
        os, "replace", lambda a, b: (events.append(("replace", str(b))), real_replace(a, b))
    )
    _small(tmp_path)
    monkeypatch.undo()
    data = {f"{name}.npy" for name in ("g", "m", *lievi.NpyWriter.SUMMARY)}
    replaced = [i for i, e in enumerate(events) if e[0] == "replace" and "/state/" in e[1]]
    assert len(replaced) == 4  # 2 chunks × 2 segments
    previous = 0
    for i in replaced:
        synced = {os.path.basename(e) for e in events[previous:i] if isinstance(e, str)}
        assert data <= synced, (data - synced, events[previous:i])
        previous = i


def test_short_write_under_a_file_size_limit(tmp_path):
    """A real `RLIMIT_FSIZE` (with `SIGXFSZ` ignored, so the write fails rather than the
    process) that cuts the last body's saves: `NpyWriter.write` raises, and the chunk's
    state is not recorded."""
    code = textwrap.dedent(
        f"""
        import resource, signal, sys
        import numpy as np
        import lievi

        b, t = 4, 201
        layout = lievi.StreamLayout(
            {{"m": ((b, t, 3), "float64")}}, b, t - 1, 1, 2, t - 1, ((3, 3), (3,)), "float64"
        )
        writer = lievi.NpyWriter({str(tmp_path)!r})
        writer.open(layout)

        def state(rows):
            n = rows.stop - rows.start
            return lievi.ChunkState(
                np.broadcast_to(np.eye(3), (n, 3, 3)), np.ones((n, 3)),
                np.zeros(n, np.int32), np.full(n, -1, np.int32), np.zeros(n, np.int64), t - 1,
            )

        m = np.ones((2, t, 3))
        writer.write(0, slice(0, 2), slice(0, t), {{"m": m}}, state(slice(0, 2)))
        header = np.load({str(tmp_path / "m.npy")!r}, mmap_mode="r").offset
        limit = header + 3 * t * 24 + 100  # inside body 3, the last
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        try:
            writer.write(1, slice(2, 4), slice(0, t), {{"m": m}}, state(slice(2, 4)))
        except OSError as error:
            print("raised:", error)
        print("chunk 1 recorded:", writer.resume_state(1) is not None)
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout
    assert "raised:" in out and "m.npy" in out, out
    assert "chunk 1 recorded: False" in out, out


def test_bodies_not_run_are_not_successes(tmp_path):
    """After a stop, a body whose chunk has not reached the horizon has `result`
    `RESULTS.not_run` and NaN for every save not yet computed; no completion marker until
    the run is finished."""
    with pytest.raises(_Stop):
        _small(tmp_path, _StopAfter(tmp_path, 1))  # chunk 0, its first of 2 segments
    written = _read(tmp_path)
    np.testing.assert_array_equal(written["result"], NOT_RUN)
    assert np.all(np.isfinite(written["m"][:2, :3])) and np.all(np.isnan(written["m"][:2, 3:]))
    assert np.all(np.isnan(written["m"][2:])) and np.all(np.isnan(written["g"][2:]))
    assert not (tmp_path / "complete.json").exists()
    _small(tmp_path)
    np.testing.assert_array_equal(np.load(tmp_path / "result.npy"), lievi.RESULTS.successful)
    complete = json.loads((tmp_path / "complete.json").read_text())
    assert complete["bodies"] == 4 and complete["results"]["successful"] == 4


def test_a_bad_body_gets_invalid_input_and_the_others_run(tmp_path):
    """A body with inadmissible inputs (here a NaN in its `m0`, and a `g0` off the group)
    gets `RESULTS.invalid_input` at step 0 and NaN saves; the stream goes on, and the
    other bodies' saves are those of a run without it."""
    _small(tmp_path / "clean")
    m0, g0 = _small_m0(), np.array(np.broadcast_to(np.eye(3), (4, 3, 3)))
    m0[1, 2] = np.nan
    g0[2] *= 2.0
    # `throw=True` (the default of every run function) raises once everything is written.
    with pytest.raises(RuntimeError, match="lievi.stream_batch: a body failed"):
        _small(tmp_path / "bad", m0=m0, g0=g0)
    bad, clean = _read(tmp_path / "bad"), _read(tmp_path / "clean")
    invalid, ok = lievi.RESULTS.invalid_input, lievi.RESULTS.successful
    np.testing.assert_array_equal(bad["result"], [ok, invalid, invalid, ok])
    np.testing.assert_array_equal(bad["failed_step"], [-1, 0, 0, -1])
    assert np.all(np.isnan(bad["m"][1:3])) and np.all(np.isnan(bad["g"][1:3]))
    for name in ("g", "m"):
        np.testing.assert_array_equal(bad[name][[0, 3]], clean[name][[0, 3]])
    assert (tmp_path / "bad" / "complete.json").exists()


def test_progress_line_is_labelled_stream_batch(tmp_path, monkeypatch, capsys):
    class _Clock:  # a second passes at every reading: the meter's delay is over at once
        now = 0.0

        @classmethod
        def monotonic(cls):
            cls.now += 1.0
            return cls.now

    monkeypatch.setattr(lievi._progress, "time", _Clock)
    _small(tmp_path, progress_meter="text")
    out = capsys.readouterr().out
    assert "lievi.stream_batch: 100.00%" in out and "lievi.simulate" not in out, out


def test_batch_of_several_body_systems(tmp_path):
    """Each body of the batch a system of two rotors (`m0` `(batch, 2, 3)`): streamed as
    `simulate_batch` runs it."""
    system = lievi.RigidRotors(jnp.array([[1.0, 2.0, 3.0], [2.0, 2.5, 1.5]]))
    m0 = np.random.default_rng(4).normal(size=(2, 2, 3))
    g0 = np.broadcast_to(np.eye(3), (2, 2, 3, 3))
    kwargs = dict(h=0.05, n_steps=8, save=lievi.Save(every=2))
    lievi.stream_batch(
        system,
        lievi.LiePoissonSplitting(),
        g0,
        m0,
        writer=lievi.NpyWriter(tmp_path),
        segment_steps=4,
        **kwargs,
    )
    solution = lievi.simulate_batch(system, lievi.LiePoissonSplitting(), g0, m0, **kwargs)
    written = _read(tmp_path)
    assert written["g"].shape == (2, 5, 2, 3, 3) and written["m"].shape == (2, 5, 2, 3)
    np.testing.assert_allclose(written["g"], solution.g, rtol=0, atol=1e-14)
    np.testing.assert_allclose(written["m"], solution.m, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(written["result"], solution.result)
