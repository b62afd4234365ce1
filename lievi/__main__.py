"""`python -m lievi <command> [options]`: see `lievi._cli`."""

import sys

from ._cli import build_parser as build_parser
from ._cli import main as main
from ._cli.main import persistent_cache

if __name__ == "__main__":
    if hasattr(sys.stdout, "reconfigure"):
        # The table uses Π, ‖·‖, …: never crash on a terminal that cannot show them.
        sys.stdout.reconfigure(errors="replace")
    persistent_cache()
    sys.exit(main())
