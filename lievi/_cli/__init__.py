"""Command line: `python -m lievi <command> [options]`.

Commands:

- `demo`: every integrator on the Hairer–Lubich–Wanner rigid body (or, with
  `--problem heavy-top`, an asymmetric heavy top), with errors against a reference
  solution, the energy error, conservation drifts and timings; `--problem control`:
  optimal rest-to-rest reorientation of a rigid body, with gradients through the
  integrator (`python -m lievi demo --help`).

Modules, one job each: `main` (parser, checks, dispatch), `arguments` (the `demo` options
and their checks), `problems` (the test problems), `demo` (the table of integrators),
`report` (its text and JSON), `control` (the control problem), `plots` (the figures).
"""

from .main import build_parser as build_parser
from .main import main as main
