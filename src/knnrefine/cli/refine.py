"""knnrefine refine: points in, mesh files (and optionally a picture and a certificate) out."""

import os
import time

from ..errors import InputError
from .common import (
    MESHES,
    PICTURES,
    add_input_options,
    add_random_state_option,
    add_refine_options,
    check_outputs,
    in_space,
    periodic_of,
    plural,
    read_input,
    refine_with_progress,
    summary,
)

HELP = "refine a file of points into a mesh"
EXAMPLES = """examples:
  knnrefine refine angles.csv -k 50 --periodic --box 0 0 360 360 -o angles.npz \\
      -o angles.vtu --plot angles.png --certify
  knnrefine refine quakes.csv --sphere -k 30 --radius 6371.0088 -o world.npz \\
      -o world.geojson --certify
  cat points.txt | knnrefine refine - -k 10 -o mesh.geojson
  knnrefine refine chi.csv --columns chi1,chi2,chi3 -k 20 --periodic \\
      --box 0 0 0 360 360 360 -o chi.vtu -o chi.npz --certify
  knnrefine refine all.csv --start old.npz -o new.npz

outputs (by extension): .npz (knnrefine's lossless format), .vtu/.vtk/.xdmf (ParaView),
.geojson (GIS), .csv (the vertices); in space (three --columns): .npz, .vtu, .vtk; on the
sphere: .npz, .vtu/.vtk (the unit sphere), .geojson (WGS84, cut at the antimeridian), .csv"""


def add_arguments(parser):
    add_input_options(parser)
    add_refine_options(parser)
    parser.add_argument(
        "-o",
        "--output",
        action="append",
        default=[],
        metavar="FILE",
        help="write the mesh here (repeatable); default: <points>-k<K>.npz",
    )
    parser.add_argument(
        "--start",
        metavar="MESH",
        help="continue this mesh (.npz, refined from the first rows of the points, in their "
        "order; the rows after them are new): its k, tau, box and floor are kept",
    )
    parser.add_argument("--plot", metavar="PICTURE", help="also draw it (.png, .svg or .pdf)")
    parser.add_argument(
        "--certify", action="store_true", help="also certify the mesh and print the report"
    )
    add_random_state_option(parser, "--certify's probes")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")


def run(args):
    from .. import certify, io
    from ..plot import save_plot, save_slices

    outputs = args.output or [_default_output(args.points, args.k)]
    check_outputs(
        [(p, MESHES, "meshes") for p in outputs]
        + ([(args.plot, PICTURES, "pictures")] if args.plot else []),
        args,
    )
    periodic_of(args)
    if in_space(args):
        from ..io import WRITERS3

        for path in outputs:
            if os.path.splitext(path)[1].lower() not in WRITERS3:
                raise InputError(
                    f"{path}: a mesh in space is written as {', '.join(sorted(WRITERS3))}"
                )
    start = None
    if args.start:
        if os.path.splitext(args.start)[1].lower() != ".npz":
            raise InputError(f"--start {args.start}: a mesh to continue is a .npz file "
                             "(knnrefine's lossless format, which keeps its torus)")  # fmt: skip
        start = io.read_mesh(args.start)
    t0 = time.perf_counter()
    points, weights, names = read_input(args)
    if not args.quiet:
        print(
            f"read {plural(len(points), 'point')} from {args.points} in "
            f"{time.perf_counter() - t0:.2f} s"
        )
    mesh, seconds = refine_with_progress(points, args, args.quiet, weights, start)
    for path in outputs:
        io.write_mesh(mesh, path, force=args.force)
    if args.plot and mesh.dim == 3:
        save_slices(mesh, args.plot, points=points, force=args.force)
    elif args.plot:
        save_plot(mesh, args.plot, points=points, force=args.force, labels=names)
    if not args.quiet:
        print(summary(mesh, seconds))
        print("  wrote " + ", ".join(outputs + ([args.plot] if args.plot else [])))
    if args.certify:
        cert = certify(mesh, points, weights=weights, workers=args.workers,
                       random_state=args.random_state)  # fmt: skip
        print(cert)
        return 0 if cert.passed else 3
    return 0


def _default_output(points, k):
    stem = "points" if points == "-" else os.path.splitext(os.path.basename(points))[0]
    return f"{stem}-k{k}.npz" if k is not None else f"{stem}-mesh.npz"
