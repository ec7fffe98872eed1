"""The ``bfpsf`` command: a thin layer over the library (parse, call, write).

Each sub-command lives in its own module ``bfpsf.cli.<name>`` that defines
``add_parser(subparsers)`` (returning the sub-parser) and ``run(args)`` (returning an exit code).
"""

import argparse
import importlib
import sys

from .. import __version__
from ..errors import BFPSFError

#: Sub-commands in data-flow order; each name is a module of this package.
COMMANDS = ["simulate", "calibrate", "measure", "slope", "psf", "photometry", "validate",
            "diagnose"]




def build_parser():
    parser = argparse.ArgumentParser(
        prog="bfpsf", description="Brighter-fatter aware PSF models (Guyonnet et al. 2015).")
    parser.add_argument("--version", action="version", version=f"bfpsf {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        module = importlib.import_module(f"{__name__}.{name}")
        sub = module.add_parser(subparsers)
        sub.set_defaults(_run=module.run)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "_run"):
        parser.print_help()
        return 2
    try:
        return args._run(args) or 0
    except BFPSFError as error:
        print(f"bfpsf {args.command}: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
