"""The ``sdp`` entry point (also ``python -m sdp_cli``): imports the command line itself, so that Ctrl-C
during start-up (torch, casadi and pinocchio take seconds to import) is "Interrupted." and exit code 130 like
Ctrl-C at any later time, not a ``KeyboardInterrupt`` traceback."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    try:
        from sdp_cli.cli import main as cli_main

        return cli_main(argv)
    except KeyboardInterrupt:
        sys.stderr.write("Interrupted.\n")
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
