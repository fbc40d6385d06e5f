"""knnrefine density: the kNN density estimate on a grid, and its picture."""

import os
import time

import numpy as np

from .common import add_input_options, add_mesh_option, add_refine_options, mesh_for

HELP = "estimate the kNN density k / (n pi d_Pk^2) on a grid"
EXAMPLES = """examples:
  knnrefine density quakes.csv --columns lon,lat --periodic-x --box -180 -90 180 90 \\
      -o density.npz --plot density.png
  knnrefine density points.npy --mesh mesh.npz --grid 1024 -o density.csv

the density integrates to 1 over the box; -k defaults to sqrt(n) / 2. Outputs: .npz (xs, ys,
density, d_pk on the grid), .csv (x, y, density, d_pk per grid cell), pictures (.png .svg .pdf)"""


def add_arguments(parser):
    add_input_options(parser)
    add_refine_options(
        parser, k_required=False, k_help="which nearest neighbour (default sqrt(n) / 2)"
    )
    add_mesh_option(parser)
    parser.add_argument(
        "--grid",
        type=int,
        nargs="+",
        default=[512],
        metavar="N",
        help="grid cells per axis (one number, or nx ny; default 512)",
    )
    parser.add_argument(
        "-o",
        "--output",
        action="append",
        default=[],
        metavar="FILE",
        help="write the grid (.npz or .csv; repeatable)",
    )
    parser.add_argument("--plot", metavar="PICTURE", help="draw the density (.png .svg .pdf)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")


def run(args):
    from .. import io
    from ..density import KnnDensity, default_k
    from ..plot import figure_size, plot_density, save_figure
    from .common import PICTURES, UsageError, check_outputs, plural, read_input

    if not args.output and not args.plot:
        raise UsageError("nothing to write: give -o FILE and/or --plot PICTURE")
    if len(args.grid) not in (1, 2) or min(args.grid) < 1:
        raise UsageError(
            f"--grid takes one or two positive numbers of cells (N, or NX NY), got "
            f"{' '.join(map(str, args.grid))}"
        )
    check_outputs(
        [(p, (".npz", ".csv"), "grids") for p in args.output]
        + ([(args.plot, PICTURES, "pictures")] if args.plot else []),
        args.force,
    )
    nx, ny = (args.grid * 2)[:2]
    points, names = read_input(args)
    mesh, _ = mesh_for(args, points, default_k)
    t0 = time.perf_counter()
    density = KnnDensity(mesh, points)
    xs, ys, d = density.distance.grid((ny, nx))
    f = density.constant / d**2
    seconds = time.perf_counter() - t0
    for path in args.output:
        ext = os.path.splitext(path)[1].lower()
        if ext == ".npz":
            io.atomic_write(
                path,
                args.force,
                lambda tmp: np.savez_compressed(
                    tmp,
                    xs=xs,
                    ys=ys,
                    density=f,
                    d_pk=d,
                    k=mesh.k,
                    n=len(points),
                    box=np.array(mesh.box),
                    periodic=np.array(mesh.periodic),
                ),
            )
        else:
            gx, gy = np.meshgrid(xs, ys)
            io.write_table(
                path,
                {
                    names[0]: gx.ravel(),
                    names[1]: gy.ravel(),
                    "density": f.ravel(),
                    "d_pk": d.ravel(),
                },
                args.force,
            )
    if args.plot:
        save_figure(
            args.plot,
            figure_size(mesh),
            lambda ax: plot_density(density, ax, shape=(ny, nx), labels=names),
            force=args.force,
        )
    if not args.quiet:
        err = density.distance.error()
        print(
            f"kNN density of n = {plural(len(points), 'point')}, k = {mesh.k}, on a {nx} x {ny} "
            f"grid from m = {plural(len(mesh.vertices), 'mesh vertex', 'mesh vertices')} in "
            f"{seconds:.2f} s"
        )
        print(
            f"  d_Pk interpolated from exact values at {len(density.distance.nodes):,} nodes: "
            f"relative error median {err['median']:.4f}, worst {err['worst']:.3f} "
            f"({err['probes']:,} probes)"
        )
        print("  wrote " + ", ".join(args.output + ([args.plot] if args.plot else [])))
    return 0
