"""knnrefine certify: check a mesh file against its points, independently of the engine."""

import json

from .common import add_input_options, add_random_state_option, add_workers_option

HELP = "certify a mesh (.npz) against its points"
EXAMPLES = """examples:
  knnrefine certify angles.npz angles.csv
  knnrefine certify world.npz quakes.csv
  knnrefine certify mesh.npz points.npy --json certificate.json

a mesh on the sphere (world.npz, from 'knnrefine refine quakes.csv --sphere ...') reads its
points' longitude and latitude columns by name.

exit status: 0 when every guarantee holds (above the resolution floor), 3 when one fails,
1 on bad input"""


def add_arguments(parser):
    parser.add_argument("mesh", help="a mesh written by 'knnrefine refine' (.npz)")
    add_input_options(parser)
    parser.add_argument("--json", metavar="FILE", help="also write the certificate as JSON")
    parser.add_argument(
        "--samples",
        type=int,
        default=100_000,
        help="stratified probes inside the triangles (default 100000)",
    )
    add_workers_option(parser)
    add_random_state_option(parser, "the probes")
    parser.add_argument("--force", action="store_true", help="overwrite an existing JSON file")


def run(args):
    from .. import certify, io
    from .common import UsageError, check_outputs, read_input

    if args.samples < 1:
        raise UsageError(f"--samples must be a positive number of probes, got {args.samples}")
    if args.json:
        check_outputs([(args.json, (".json",), "certificates")], args)
    mesh = io.read_mesh(args.mesh)
    args.sphere = mesh.on_sphere  # its points: longitude and latitude, found by name
    points, weights, _ = read_input(args)
    cert = certify(mesh, points, samples=args.samples, weights=weights, workers=args.workers,
                   random_state=args.random_state)  # fmt: skip
    if args.json:
        text = json.dumps(cert.to_dict(), indent=1)
        io.write_text(args.json, text, force=args.force)
    if not args.quiet:
        print(cert)
    return 0 if cert.passed else 3
