"""Progress meters for `progress_meter=`, in the manner of diffrax's: the base sends the
fraction done from the compiled loop and keeps one record per run; a meter shows it."""

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
    """The base of the progress meters (no arrays: static to `jit`). A subclass shows the
    progress: `_start()` returns the host-side state of a new run, `_show(state,
    fraction)` shows one update (each `fraction` in `[0, 1]` once), `_close(state)`."""

    reports: ClassVar[bool] = True

    def report(self, k, n_steps):
        """Send `k / n_steps` to the host about every 1% of the steps, from the compiled
        loop (`jax.debug.callback`); returns `k` ordered after the report."""
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
        """Show `fraction` done, from the host (`stream_batch`'s segments)."""
        if self.reports:
            _on_host(self, fraction)

    @abc.abstractmethod
    def _start(self) -> Any: ...

    @abc.abstractmethod
    def _show(self, state, fraction: float) -> None: ...

    @abc.abstractmethod
    def _close(self, state) -> None: ...


# The run in progress of each meter, `[state, last fraction]` (equal meters share it, as
# they share compiled code; a meter's runs follow each other).
_RUNS: dict[AbstractProgressMeter, list] = {}


def _on_host(meter: AbstractProgressMeter, fraction) -> None:
    # Under `vmap` the fraction arrives batched, identical in every lane.
    fraction = float(np.max(np.asarray(fraction)))
    run = _RUNS.get(meter)
    if run is not None and fraction == run[1]:
        return  # the same update again, from another lane of a vmapped run
    if run is None or fraction == 0.0:
        if run is not None:
            meter._close(run[0])  # a run that never reached 100% (an interrupted one)
        run = _RUNS[meter] = [meter._start(), -1.0]
    run[1] = fraction
    meter._show(run[0], fraction)
    if fraction >= 1.0:
        meter._close(run[0])
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
    """The percentage done on one line of standard output, rewritten in place.

    **Arguments:**

    - `delay`: seconds a run must have taken before anything is printed (default 1).
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
    """A tqdm progress bar (on standard error), one per run; needs tqdm
    (`pip install tqdm`, or `lievi[progress]`).

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
    """The meter of `progress_meter=`: a meter, or `False`/`None`, `"text"`, `"tqdm"`,
    `True` (tqdm where installed, else text), its meter labelled `label`."""
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
