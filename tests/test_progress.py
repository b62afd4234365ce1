"""`simulate(..., progress_meter=...)`: progress reported from inside the compiled loop.

The text meter writes one line, rewritten in place, and only once a run has taken its
`delay` (1 s by default): a quick run prints nothing.
"""

import re
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import hlw_problem
from lievi import _progress
from lievi._progress import as_progress_meter

SPLITTING = lievi.LiePoissonSplitting()


def printed(capsys) -> str:
    jax.effects_barrier()  # wait for the host callbacks
    return capsys.readouterr().out


def percents(line: str) -> list[float]:
    return [float(x) for x in re.findall(r"lievi\.simulate:\s+([\d.]+)%", line)]


def test_quick_run_prints_nothing_and_values_do_not_change(capsys):
    body, g0, m0 = hlw_problem()
    kwargs = dict(h=0.1, n_steps=400, save=lievi.Save(every=4))
    plain = lievi.simulate(body, SPLITTING, g0, m0, **kwargs)
    assert printed(capsys) == ""
    for meter in ("text", lievi.TextProgressMeter()):  # well under the 1 s delay
        metered = lievi.simulate(body, SPLITTING, g0, m0, progress_meter=meter, **kwargs)
        assert printed(capsys) == ""
        np.testing.assert_array_equal(metered.m, plain.m)
        np.testing.assert_array_equal(metered.g, plain.g)


def test_text_meter_updates_one_line_in_place(capsys):
    body, g0, m0 = hlw_problem()
    meter = lievi.TextProgressMeter(delay=0.0)
    lievi.simulate(
        body, SPLITTING, g0, m0, h=0.1, n_steps=400, save=lievi.Save(every=4), progress_meter=meter
    )
    out = printed(capsys)
    assert out.count("\n") == 1 and out.endswith("\n")  # one line ...
    updates = out.rstrip("\n").split("\r")[1:]  # ... rewritten after each carriage return
    values = [p for u in updates for p in percents(u)]
    assert len(values) == len(updates)
    assert values[0] == 0.0 and values[-1] == 100.0
    assert np.all(np.diff(values) > 0) and 50 <= len(values) <= 102  # about every 1%


def test_text_meter_starts_once_the_delay_has_passed(capsys, monkeypatch):
    """A clock that advances 0.02 s per reading: nothing for the first second (about half
    the updates), then the same line updated to 100%."""
    clock = iter(0.02 * np.arange(10_000))
    monkeypatch.setattr(_progress, "time", types.SimpleNamespace(monotonic=lambda: next(clock)))
    body, g0, m0 = hlw_problem()
    lievi.simulate(body, SPLITTING, g0, m0, h=0.1, n_steps=100, progress_meter="text")
    out = printed(capsys)
    values = percents(out)
    assert out.count("\n") == 1 and out.startswith("\r")
    assert 20 <= values[0] <= 80 and values[-1] == 100.0, values


def test_meter_under_vmap(capsys):
    body, g0, m0 = hlw_problem()
    meter = lievi.TextProgressMeter(delay=0.0)
    run = jax.vmap(
        lambda m: lievi.simulate(body, SPLITTING, g0, m, h=0.1, n_steps=50, progress_meter=meter).m[
            -1
        ]
    )
    out = run(jnp.stack([m0, 2 * m0]))
    assert out.shape == (2, 3) and jnp.all(jnp.isfinite(out))
    values = percents(printed(capsys))
    assert values[0] == 0.0 and values[-1] == 100.0
    assert np.all(np.diff(values) > 0)  # each update once, not once per lane


def _report_results_unused(jaxpr) -> int:
    """How many `cond`s that send a report (a `debug_callback` inside) have no result read
    later in the same jaxpr (the loop's bodies included)."""
    unused = 0
    for i, eqn in enumerate(jaxpr.eqns):
        subs = [
            p.jaxpr
            for p in jax.tree.leaves(eqn.params, is_leaf=lambda x: hasattr(x, "jaxpr"))
            if hasattr(p, "jaxpr") and hasattr(p.jaxpr, "eqns")
        ]
        if eqn.primitive.name == "cond" and any(
            e.primitive.name == "debug_callback" for sub in subs for e in sub.eqns
        ):
            later = {id(v) for e in jaxpr.eqns[i + 1 :] for v in e.invars}
            later |= {id(v) for v in jaxpr.outvars}
            unused += not any(id(v) in later for v in eqn.outvars)
        for sub in subs:
            unused += _report_results_unused(sub)
    return unused


def test_reports_are_ordered_before_the_loop_goes_on():
    """Every report's result is read by what follows (the 0 at the start of a traced run
    included): a report nothing depends on may reach the host after later ones (seen on a
    loaded machine: a run under `vmap` whose 0% came after its 2%)."""
    body, g0, m0 = hlw_problem()
    meter = lievi.TextProgressMeter(delay=0.0)
    jaxpr = jax.make_jaxpr(
        jax.vmap(
            lambda m: (
                lievi.simulate(body, SPLITTING, g0, m, h=0.1, n_steps=50, progress_meter=meter).m
            )
        )
    )(jnp.stack([m0, 2 * m0]))
    assert _report_results_unused(jaxpr.jaxpr) == 0


def test_shorthands():
    assert as_progress_meter(False) == lievi.NoProgressMeter()
    assert as_progress_meter(None) == lievi.NoProgressMeter()
    assert as_progress_meter("text") == lievi.TextProgressMeter()
    assert isinstance(as_progress_meter(True), (lievi.TqdmProgressMeter, lievi.TextProgressMeter))
    meter = lievi.TextProgressMeter(delay=5.0, prefix="run")
    assert as_progress_meter(meter) is meter


def test_bad_progress_meter():
    body, g0, m0 = hlw_problem()
    for bad in ("bar", 1, object()):
        with pytest.raises(ValueError, match="`progress_meter`"):
            lievi.simulate(body, lievi.DEP(), g0, m0, h=0.1, n_steps=2, progress_meter=bad)
    with pytest.raises(ValueError, match="delay"):
        lievi.TextProgressMeter(delay=-1.0)


def test_tqdm_meter_without_tqdm(monkeypatch):
    monkeypatch.setitem(sys.modules, "tqdm", None)  # as if not installed
    with pytest.raises(ImportError, match="pip install tqdm"):
        lievi.TqdmProgressMeter()
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="needs tqdm"):
        lievi.simulate(body, lievi.DEP(), g0, m0, h=0.1, n_steps=2, progress_meter="tqdm")
    assert as_progress_meter(True) == lievi.TextProgressMeter()


def test_tqdm_meter(capsys):
    pytest.importorskip("tqdm")
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, SPLITTING, g0, m0, h=0.1, n_steps=100, progress_meter="tqdm")
    jax.effects_barrier()
    assert "lievi.simulate" in capsys.readouterr().err
    assert jnp.all(jnp.isfinite(sol.m))


def test_tqdm_meter_with_a_stand_in_tqdm(monkeypatch):
    """With a stand-in `tqdm.auto.tqdm`: one bar per run, moved to each reported
    percentage once (also under `vmap`) and closed at 100%."""
    bars = []

    class Bar:
        def __init__(self, total, desc, unit):
            self.n, self.closed, self.positions = 0, False, []
            bars.append(self)

        def refresh(self):
            self.positions.append(self.n)

        def close(self):
            self.closed = True

    fake = types.ModuleType("tqdm.auto")
    fake.tqdm = Bar
    monkeypatch.setitem(sys.modules, "tqdm", types.ModuleType("tqdm"))
    monkeypatch.setitem(sys.modules, "tqdm.auto", fake)
    body, g0, m0 = hlw_problem()
    meter = lievi.TqdmProgressMeter()
    run = jax.vmap(
        lambda m: lievi.simulate(body, SPLITTING, g0, m, h=0.1, n_steps=20, progress_meter=meter)
    )
    for _run in range(2):  # two runs in a row
        run(jnp.stack([m0, 2 * m0]))
        jax.effects_barrier()
    assert len(bars) == 2
    for bar in bars:
        assert bar.closed and bar.positions == [5.0 * k for k in range(21)], bar.positions


@pytest.mark.extended  # 13–14 s each
@pytest.mark.parametrize("fast", [True, False])
def test_batch_meter_updates_one_line(capsys, fast):
    """`simulate_batch(progress_meter=...)`: one line for the whole batch, on the fast path
    and the generic one, each percentage once; the values are those of a run without it."""
    body, g0, m0 = hlw_problem()
    m0s = jnp.stack([m0, 2 * m0, -m0, 0.5 * m0])
    kwargs = dict(
        h=0.1, n_steps=200, save=lievi.Save(every=20), tuning=lievi.advanced.Tuning(fast=fast)
    )
    plain = lievi.simulate_batch(body, lievi.DEP(), g0, m0s, **kwargs)
    meter = lievi.TextProgressMeter(delay=0.0, prefix="batch")
    metered = lievi.simulate_batch(body, lievi.DEP(), g0, m0s, progress_meter=meter, **kwargs)
    out = printed(capsys)
    assert out.count("\n") == 1 and out.endswith("\n")
    values = [float(x) for x in re.findall(r"batch:\s+([\d.]+)%", out)]
    assert values[0] == 0.0 and values[-1] == 100.0
    assert np.all(np.diff(values) > 0) and 50 <= len(values) <= 102
    np.testing.assert_array_equal(metered.m, plain.m)
    np.testing.assert_array_equal(metered.g, plain.g)


def test_batch_bad_progress_meter():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="`progress_meter`"):
        lievi.simulate_batch(
            body,
            lievi.DEP(),
            g0,
            m0[None],
            h=0.1,
            n_steps=2,
            progress_meter="bar",
            save=lievi.Save(every=2),
        )
