"""Progress meters for `simulate(..., progress_meter=...)`, in the manner of diffrax's.

A meter is a small `eqx.Module` (no arrays, so it is static to `jit`). The abstract base
owns the behaviour: inside the compiled loop it sends the fraction of steps done to the
host about every 1% of the steps (`jax.debug.callback`, so it also works under an outer
`jit`), drops the repeats that arrive from the lanes of a `vmap`-ed run, and keeps one
record per run (started by the fraction 0, ended by 1). The concrete meters only say how
to show it: `NoProgressMeter` (nothing; no callback is compiled at all),
`TextProgressMeter` (one line, rewritten in place) and `TqdmProgressMeter` (a tqdm bar).
"""

from __future__ import annotations

import abc
import importlib.util
import time
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class AbstractProgressMeter(eqx.Module):
    """The base of the progress meters: when and what to report, from the compiled loop.

    A subclass shows the progress: `_start()` returns the host-side state of a new run,
    `_show(state, fraction)` shows one update (`fraction` in `[0, 1]`, each value once per
    run), `_close(state)` ends the run.
    """

    reports: ClassVar[bool] = True

    def report(self, k, n_steps):
        """Send `k / n_steps` to the host about every 1% of the steps (`k`, traced, counts
        the steps done; `n_steps` static or traced: an eager run's horizon is traced, see
        `lievi._loop`). Called inside `simulate`'s loop.

        Returns `k`, after the report: what is computed from the returned value is ordered
        after it (the callbacks are otherwise unordered)."""
        if not self.reports:
            return k
        stride = jnp.maximum(1, n_steps // 100)

        def send(k):
            jax.debug.callback(_on_host, self, k / n_steps)
            # Not the operand itself, or XLA drops the dependency (both branches would
            # return their operand) and may run the report alongside what follows.
            return jax.lax.optimization_barrier(k)

        return jax.lax.cond((k % stride == 0) | (k == n_steps), send, lambda k: k, k)

    def show(self, fraction: float) -> None:
        """Show `fraction` done, from the host: for a loop run in Python (`stream_batch`'s
        segments). The same record as `report`'s: a run starts at the first update (or at
        0) and ends at 1."""
        if self.reports:
            _on_host(self, fraction)

    @abc.abstractmethod
    def _start(self) -> Any:
        """The state of a new run (on the host)."""

    @abc.abstractmethod
    def _show(self, state, fraction: float) -> None:
        """Show `fraction` done."""

    @abc.abstractmethod
    def _close(self, state) -> None:
        """End the run (after `_show(state, 1.0)`)."""


class _Run:
    """The host-side record of the run in progress of one meter."""

    def __init__(self, state):
        self.state = state
        self.last = -1.0


# One record per meter (equal meters share it, as they share compiled code); runs of one
# meter follow each other, so one record at a time is enough.
_RUNS: dict[AbstractProgressMeter, _Run] = {}


def _on_host(meter: AbstractProgressMeter, fraction) -> None:
    # Under `vmap` the fraction arrives batched, identical in every lane.
    fraction = float(np.max(np.asarray(fraction)))
    run = _RUNS.get(meter)
    if run is not None and fraction == run.last:
        return  # the same update again, from another lane of a vmapped run
    if run is None or fraction == 0.0:
        if run is not None:
            meter._close(run.state)  # a run that never reached 100% (an interrupted one)
        run = _RUNS[meter] = _Run(meter._start())
    run.last = fraction
    meter._show(run.state, fraction)
    if fraction >= 1.0:
        meter._close(run.state)
        del _RUNS[meter]


class NoProgressMeter(AbstractProgressMeter):
    """Report nothing (the default of `simulate`): no callback is compiled into the loop."""

    reports: ClassVar[bool] = False

    def _start(self):
        return None

    def _show(self, state, fraction):
        pass

    def _close(self, state):
        pass


class _TextState:
    def __init__(self):
        self.started = time.monotonic()
        self.shown = False


class TextProgressMeter(AbstractProgressMeter):
    """The percentage done on one line of standard output, rewritten in place (a carriage
    return before each update, a newline at the end).

    **Arguments:**

    - `delay`: seconds a run must have taken before anything is printed (default 1): a run
      that finishes sooner prints nothing at all.
    - `prefix`: the text before the percentage.
    """

    delay: float = eqx.field(default=1.0, static=True)
    prefix: str = eqx.field(default="lievi.simulate", static=True)

    def __check_init__(self):
        if not (isinstance(self.delay, (int, float)) and self.delay >= 0):
            raise ValueError(f"`delay` must be a number of seconds ≥ 0, got {self.delay!r}.")

    def _start(self):
        return _TextState()

    def _show(self, state, fraction):
        if not state.shown and time.monotonic() - state.started < self.delay:
            return
        state.shown = True
        print(f"\r{self.prefix}: {100 * fraction:6.2f}%", end="", flush=True)

    def _close(self, state):
        if state.shown:
            print(flush=True)


def _has_tqdm() -> bool:
    try:
        return importlib.util.find_spec("tqdm") is not None
    except ValueError:  # imported already, by a loader that sets no spec
        return True


class TqdmProgressMeter(AbstractProgressMeter):
    """A tqdm progress bar (on standard error), one per run. Needs tqdm
    (`pip install tqdm`, or `lievi[progress]`); checked when the meter is made.

    **Arguments:**

    - `desc`: the bar's label.
    """

    desc: str = eqx.field(default="lievi.simulate", static=True)

    def __check_init__(self):
        if not _has_tqdm():
            raise ImportError(
                "TqdmProgressMeter needs tqdm: `pip install tqdm` (or `lievi[progress]`), "
                "or use lievi.TextProgressMeter()."
            )

    def _start(self):
        from tqdm.auto import tqdm

        return tqdm(total=100, desc=self.desc, unit="%")

    def _show(self, bar, fraction):
        bar.n = round(100 * fraction, 2)
        bar.refresh()

    def _close(self, bar):
        bar.close()


def as_progress_meter(progress_meter, label: str = "lievi.simulate") -> AbstractProgressMeter:
    """The meter of `simulate`'s `progress_meter` argument: a meter as it is, or a
    shorthand: `False`/`None` (`NoProgressMeter`), `"text"` (`TextProgressMeter`),
    `"tqdm"` (`TqdmProgressMeter`), `True` (tqdm where it is installed, else text); the
    meter a shorthand makes shows `label` (the entry point's name)."""
    if isinstance(progress_meter, AbstractProgressMeter):
        return progress_meter
    if progress_meter is False or progress_meter is None:
        return NoProgressMeter()
    if progress_meter is True:
        return TqdmProgressMeter(desc=label) if _has_tqdm() else TextProgressMeter(prefix=label)
    if isinstance(progress_meter, str) and progress_meter == "text":
        return TextProgressMeter(prefix=label)
    if isinstance(progress_meter, str) and progress_meter == "tqdm":
        try:
            return TqdmProgressMeter(desc=label)
        except ImportError as error:
            raise ValueError(
                "`progress_meter='tqdm'` needs tqdm: `pip install tqdm`, or pass "
                "progress_meter='text'."
            ) from error
    raise ValueError(
        "`progress_meter` must be a lievi.NoProgressMeter, TextProgressMeter or "
        f"TqdmProgressMeter, or False, True, 'text' or 'tqdm'; got {progress_meter!r}."
    )
