"""Command line: `python -m lievi <command> [options]`.

Commands:

- `demo`: every integrator on the Hairer–Lubich–Wanner rigid body (or, with
  `--problem heavy-top`, an asymmetric heavy top), with errors against a reference
  solution, the energy error, conservation drifts and timings; `--problem control`:
  optimal rest-to-rest reorientation of a rigid body, with gradients through the
  integrator (`python -m lievi demo --help`).

To add a command, add an entry to `_COMMANDS`: its name, a one-line help, a function
that adds its options to an `argparse` parser, and the name of a module in `lievi`
whose `main(args)` runs it and returns the exit status. Modules are imported lazily.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (help, module with `add_arguments(parser)` and `main(args) -> int`)
_COMMANDS = {
    "demo": (
        "run every integrator on the HLW rigid body (or --problem heavy-top) and print "
        "errors, drifts and timings; --problem control: optimal reorientation",
        "lievi._demo",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m lievi",
        description="lievi: variational integrators on Lie groups (JAX).",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (help_text, module_name) in _COMMANDS.items():
        sub = commands.add_parser(name, help=help_text, description=help_text)
        importlib.import_module(module_name).add_arguments(sub)
        sub.set_defaults(_module=module_name)
    return parser


def main(argv: list[str] | None = None) -> int:
    # float64 before any array is created (importing lievi creates none).
    import jax

    jax.config.update("jax_enable_x64", True)
    args = build_parser().parse_args(argv)
    return importlib.import_module(args._module).main(args)


if __name__ == "__main__":
    if hasattr(sys.stdout, "reconfigure"):
        # The table uses Π, ‖·‖, …: never crash on a terminal that cannot show them.
        sys.stdout.reconfigure(errors="replace")
    sys.exit(main())
