"""The command line's entry: the parser of `python -m lievi <command> [options]`, the
checks of the options before any computation, and the dispatch to the command.

To add a command, add an entry to `COMMANDS`: its name, a one-line help, a function that
adds its options to an `argparse` parser, one that lists what is wrong with the parsed
options (each reported in one line by `parser.error`, exit status 2), and one that runs
it and returns the exit status.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import NamedTuple

from . import arguments


class Command(NamedTuple):
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    check: Callable[[argparse.Namespace], list[str]]
    run: Callable[[argparse.Namespace], int]


def run_demo(args: argparse.Namespace) -> int:
    """The `demo` command: the table of integrators, or the control problem (imported
    only when it runs)."""
    if args.problem == "control":  # an optimisation, not a table of integrators
        from .control import main
    else:
        from .demo import main
    return main(args)


COMMANDS = {
    "demo": Command(
        "run every integrator on the HLW rigid body (or --problem heavy-top) and print "
        "errors, drifts and timings; --problem control: optimal reorientation",
        arguments.add_arguments,
        arguments.check_arguments,
        run_demo,
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m lievi",
        description="lievi: variational integrators on Lie groups (JAX).",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, command in COMMANDS.items():
        sub = commands.add_parser(name, help=command.help, description=command.help)
        command.add_arguments(sub)
        sub.set_defaults(_command=command, _parser=sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse `argv` (default `sys.argv[1:]`), check it and run the command; returns the
    exit status. Bad options exit with status 2 and one line saying what is wrong."""
    # float64 before any array is created (importing lievi creates none).
    import jax

    jax.config.update("jax_enable_x64", True)
    args = build_parser().parse_args(argv)
    if messages := args._command.check(args):
        args._parser.error("; ".join(messages))
    return args._command.run(args)


def persistent_cache() -> None:
    """JAX's persistent compilation cache for `python -m lievi`'s own process (a demo run
    again loads its programs instead of compiling them): in `$LIEVI_CACHE_DIR`, or
    `~/.cache/lievi/jax`; `LIEVI_CACHE_DIR=""` turns it off. A library does not set it for
    its users (docs/compile-times.md says how)."""
    import os
    import pathlib

    import jax

    directory = os.environ.get("LIEVI_CACHE_DIR", str(pathlib.Path.home() / ".cache/lievi/jax"))
    if directory and jax.config.jax_compilation_cache_dir is None:
        jax.config.update("jax_compilation_cache_dir", directory)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
