"""The energy error of DEP (Cayley chart) on the binary asteroid of the test suite over
long runs: is it bounded, or does it drift?

Runs `tests/test_rigid_bodies.py`'s binary (two bodies of three point masses in mutual
gravity) for `T = 3·10⁴` (3·10⁶ steps of `h = 0.01`, and 6·10⁶ of `h = 0.005`), saving
once per unit of time, and prints the mean relative energy error over each thirtieth of
the run. A drift shows as a trend across the thirty means; a modulation as a rise and fall.

    python benchmarks/binary_long_run.py      # about 7 minutes on 2 cores

Prints; its output is kept in `benchmarks/results/binary_long_run.log`.
"""

from __future__ import annotations

import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import lievi  # noqa: E402
import lievi.diagnostics as dg  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
from test_rigid_bodies import PROBLEMS  # noqa: E402


def main():
    system, g0, m0 = PROBLEMS["binary"]()
    for h, n in ((0.01, 3_000_000), (0.005, 6_000_000)):
        start = time.time()
        sol = lievi.simulate(
            system, lievi.DEP(chart="cayley"), g0, m0, h=h, n_steps=n, save_every=round(1 / h)
        )
        energy = np.asarray(dg.energy(system, sol.m, sol.g))
        error = np.abs(energy - energy[0]) / abs(energy[0])
        means = error[1:].reshape(30, -1).mean(1)
        print(
            f"h={h} T={n * h:.0f} ({time.time() - start:.0f} s), mean error per T/30:",
            " ".join(f"{x:.2e}" for x in means),
            flush=True,
        )


if __name__ == "__main__":
    main()
