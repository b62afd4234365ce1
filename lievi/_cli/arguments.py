"""The `demo` command's options, and their checks before any computation.

Each option is checked as it is parsed (a number of steps is an integer in
`[1, MAX_STEPS]`, a step size a finite, normal number > 0), then together
(`check_arguments`): the step turns the body by less than the methods' step bound, the
time `T = h·N` stays within `MAX_TIME` (the DOP853 reference runs over `[0, T]` before any
integrator), and the output paths can be written. Every problem is reported in one line
by `parser.error` (exit status 2).
"""

from __future__ import annotations

import argparse
import math
import os
import sys

import jax.numpy as jnp

from .problems import (
    CONTROL_DEFAULT_STEPS,
    CONTROL_PROBLEM,
    CONTROL_T,
    DEFAULT_H,
    DEFAULT_PROBLEM,
    DEFAULT_STEPS,
    PROBLEMS,
)

MAX_STEPS = 10**5  # integrators' runs: T = 100 at h = 1e-3
MAX_CONTROL_STEPS = 1000  # control: each step adds to every L-BFGS iteration
MAX_TIME = 1000.0  # the reference solution's cost grows with T (about 10 s per 1000)


def bounded_int(maximum: int):
    """An argparse type: an integer in `[1, maximum]`."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected an integer from 1 to {maximum}, got {text!r}"
            ) from None
        if not 1 <= value <= maximum:
            raise argparse.ArgumentTypeError(f"expected an integer from 1 to {maximum}, got {text}")
        return value

    return parse


def positive_float(text: str) -> float:
    """An argparse type: a finite, normal floating-point number > 0 (not subnormal)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    if value < sys.float_info.min:
        raise argparse.ArgumentTypeError(
            f"{text!r} is below the smallest normal float64 ({sys.float_info.min:.3g})"
        )
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `demo` subcommand's options."""
    parser.add_argument(
        "--steps",
        type=bounded_int(MAX_STEPS),
        default=None,
        metavar="N",
        help=f"number of steps (default {DEFAULT_STEPS}, i.e. T = 100 at the default h; "
        f"control: {CONTROL_DEFAULT_STEPS} over the fixed T = {CONTROL_T:g})",
    )
    parser.add_argument(
        "--h",
        type=positive_float,
        default=None,
        metavar="H",
        help=f"step size (default {DEFAULT_H}; not for control, where h = T/N)",
    )
    parser.add_argument(
        "--problem",
        choices=(*PROBLEMS, CONTROL_PROBLEM),
        default=DEFAULT_PROBLEM,
        help=f"the test problem (default {DEFAULT_PROBLEM}; heavy-top: the asymmetric heavy "
        "top; binary: a binary asteroid, two bodies in mutual gravity; control: optimal "
        "rest-to-rest reorientation, solved through the integrator)",
    )
    parser.add_argument(
        "--plot",
        metavar="FILE.png",
        default=None,
        help="save a figure: Π(t) against the reference, and |E − E₀| (needs matplotlib)",
    )
    parser.add_argument("--json", metavar="FILE.json", default=None, help="write the table as JSON")


def check_output_path(option: str, path: str) -> str | None:
    """Why `path` cannot be written (a message naming `option`), or `None` if it can.

    Checked before the run, so a typo does not cost the whole computation.
    """
    directory = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        return f"{option} {path!r} is a directory; give a file name"
    if not os.path.isdir(directory):
        return f"{option} {path!r}: the directory {directory!r} does not exist; create it first"
    if not os.access(directory, os.W_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        return f"{option} {path!r}: not writable; choose another location"
    return None


def _check_step(args: argparse.Namespace) -> str | None:
    """The step against the methods' step bound, and the time against `MAX_TIME`."""
    if args.problem == CONTROL_PROBLEM:
        if args.h is not None:
            return (
                f"--h does not apply to --problem control (the time T = {CONTROL_T:g} is "
                "fixed; choose the number of steps with --steps, h = T/N)"
            )
        if args.steps is not None and args.steps > MAX_CONTROL_STEPS:
            return f"--steps: at most {MAX_CONTROL_STEPS} for --problem control, got {args.steps}"
        return None
    problem = PROBLEMS[args.problem]
    h = problem.default_h if args.h is None else args.h
    n_steps = problem.default_steps if args.steps is None else args.steps
    system, _, m0 = problem.make()
    rate = float(jnp.linalg.norm(system.velocity(m0)))  # |ω₀|, rad per unit time
    bound = max(integrator.step_bound() for _, integrator in problem.integrators)
    if h * rate > bound:
        return (
            f"--h {h:g}: the first step turns the body by h·|ω₀| = {h * rate:.3g} rad, past "
            f"the largest step bound of the methods ({bound:.3g} rad; a rotation sampled at "
            f"π or more per step is aliased); take --h ≤ {bound / rate:.3g}"
        )
    if h * n_steps > MAX_TIME:
        return (
            f"--h {h:g} with --steps {n_steps}: T = h·N = {h * n_steps:.3g} exceeds "
            f"{MAX_TIME:g} (the DOP853 reference solves all of [0, T] before any method runs); "
            "take fewer steps or a smaller h"
        )
    return None


def check_arguments(args: argparse.Namespace) -> list[str]:
    """Every problem with the parsed `demo` options (empty: none), found before the run."""
    messages = []
    if message := _check_step(args):
        messages.append(message)
    for option, path in (("--json", args.json), ("--plot", args.plot)):
        if path and (message := check_output_path(option, path)):
            messages.append(message)
    if args.plot and not messages:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            messages.append("--plot needs matplotlib: pip install matplotlib (or lievi[plot])")
    return messages
