"""Entry point of the ``knnrefine`` console script."""

import argparse
import sys

from . import demo

SUBCOMMANDS = {"demo": demo}


def build_parser():
    parser = argparse.ArgumentParser(
        prog="knnrefine",
        description="Certified meshes carrying the k-th nearest neighbour distance.",
        epilog="example: knnrefine demo",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, module in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    from ..errors import KnnRefineError

    try:
        return SUBCOMMANDS[args.command].run(args)
    except KnnRefineError as exc:
        print(f"knnrefine: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
