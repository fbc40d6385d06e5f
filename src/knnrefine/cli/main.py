"""Entry point of the ``knnrefine`` console script: one module per subcommand."""

import argparse
import sys
import warnings

from . import certify, cluster, demo, density, persistence, plot, refine

SUBCOMMANDS = {
    "refine": refine,
    "certify": certify,
    "plot": plot,
    "density": density,
    "persistence": persistence,
    "cluster": cluster,
    "demo": demo,
}

DESCRIPTION = """Certified meshes carrying the k-th nearest neighbour distance of planar points
(kNNRefine: Gardner & Sheehy, CCCG 2016)."""
EPILOG = """examples:
  knnrefine demo
  knnrefine refine points.csv -k 20 -o mesh.npz --plot mesh.png
  knnrefine certify mesh.npz points.csv
  knnrefine plot mesh.npz -o cells.svg --cells voronoi
  knnrefine density points.csv -o density.npz --plot density.png
  knnrefine persistence ring.csv -k 30 --plot diagram.png
  knnrefine cluster points.csv -k 50 -o labels.csv --plot clusters.png

exit status: 0 success, 1 bad input, 2 usage, 3 a certificate that fails
'knnrefine COMMAND --help' shows each command's options and examples."""


def build_parser():
    # accepted before or after the command; SUPPRESS keeps a subcommand from resetting them
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=argparse.SUPPRESS,
        help="print nothing but errors",
    )
    common.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks on errors"
    )
    parser = argparse.ArgumentParser(
        prog="knnrefine",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[common],
    )
    from .. import __version__

    parser.add_argument("--version", action="version", version=f"knnrefine {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in SUBCOMMANDS.items():
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=module.HELP,
            epilog=module.EXAMPLES,
            parents=[common],
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """knnrefine's own warnings as one line, like its errors; others as Python shows them."""
    from .. import errors

    if category.__module__ == errors.__name__ or category.__name__ == "KernelCacheWarning":
        print(f"knnrefine: warning: {message}".replace("\n", " "), file=sys.stderr)
    else:
        print(warnings.formatwarning(message, category, filename, lineno, line), file=sys.stderr)


def main(argv=None):
    """Run the command line; returns the exit status (2 for usage errors, via SystemExit)."""
    args = build_parser().parse_args(argv)
    # parents share their option objects with the subcommands, so defaults are set here
    args.quiet = getattr(args, "quiet", False)
    args.debug = getattr(args, "debug", False)
    from ..errors import KnnRefineError
    from ..io import all_or_none
    from .common import UsageError

    try:
        with warnings.catch_warnings(), all_or_none():  # every output of a command, or none
            warnings.showwarning = _show_warning
            return SUBCOMMANDS[args.command].run(args)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print("knnrefine: interrupted", file=sys.stderr)
        return 130
    except UsageError as exc:
        if args.debug:
            raise
        print(f"knnrefine {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except (KnnRefineError, OSError, ImportError) as exc:
        if args.debug:
            raise
        print(f"knnrefine: error: {exc}".replace("\n", " "), file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
