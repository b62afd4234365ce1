"""`simulate(..., progress_meter=...)`: progress reported from inside the compiled loop."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import hlw_problem


def reported(capsys) -> list[float]:
    jax.effects_barrier()  # wait for the host callbacks
    return [float(x) for x in re.findall(r"lievi\.simulate:\s+([\d.]+)%", capsys.readouterr().out)]


def test_text_meter_reports_monotone_progress_and_changes_nothing(capsys):
    body, g0, m0 = hlw_problem()
    kwargs = dict(h=0.1, n_steps=400, save_every=4)
    plain = lievi.simulate(body, lievi.LiePoissonSplitting(), g0, m0, **kwargs)
    assert reported(capsys) == []
    metered = lievi.simulate(
        body, lievi.LiePoissonSplitting(), g0, m0, progress_meter="text", **kwargs
    )
    percents = reported(capsys)
    assert percents[0] == 0.0 and percents[-1] == 100.0
    assert np.all(np.diff(percents) > 0) and 50 <= len(percents) <= 102  # about every 1%
    np.testing.assert_array_equal(metered.m, plain.m)
    np.testing.assert_array_equal(metered.g, plain.g)


def test_meter_under_vmap(capsys):
    body, g0, m0 = hlw_problem()
    run = jax.vmap(
        lambda m: lievi.simulate(
            body, lievi.LiePoissonSplitting(), g0, m, h=0.1, n_steps=50, progress_meter="text"
        ).m[-1]
    )
    out = run(jnp.stack([m0, 2 * m0]))
    assert out.shape == (2, 3) and jnp.all(jnp.isfinite(out))
    percents = reported(capsys)
    assert percents[0] == 0.0 and percents[-1] == 100.0


def test_bad_progress_meter():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="`progress_meter`"):
        lievi.simulate(body, lievi.DEP(), g0, m0, h=0.1, n_steps=2, progress_meter="bar")


def test_tqdm_meter(capsys):
    pytest.importorskip("tqdm")
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(
        body, lievi.LiePoissonSplitting(), g0, m0, h=0.1, n_steps=100, progress_meter="tqdm"
    )
    jax.effects_barrier()
    assert "lievi.simulate" in capsys.readouterr().err
    assert jnp.all(jnp.isfinite(sol.m))


def test_tqdm_report_without_tqdm(monkeypatch):
    """The host side of the tqdm meter with a stand-in `tqdm.auto.tqdm`: one bar per run,
    moved to the reported percentage and closed at 100%."""
    import sys
    import types

    from lievi._simulate import _ProgressReport

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
    report = _ProgressReport("tqdm")
    for _run in range(2):  # two runs in a row
        for fraction in [0.0, 0.25, 0.25, 0.5, 1.0]:  # a repeat, as from a vmapped lane
            report(np.array([fraction, fraction]))
    assert len(bars) == 2
    assert all(bar.closed and bar.positions == [0.0, 25.0, 50.0, 100.0] for bar in bars)
