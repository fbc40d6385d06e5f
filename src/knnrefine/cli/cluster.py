"""knnrefine cluster: ToMATo clusters of the points through the mesh."""

import numpy as np

from .common import add_input_options, add_mesh_option, add_refine_options, mesh_for

HELP = "cluster the points by the modes of their kNN density (ToMATo on the mesh)"
EXAMPLES = """examples:
  knnrefine cluster s1.csv -k 50 -o labels.csv --plot clusters.png
  knnrefine cluster points.npy --mesh mesh.npz --n-clusters 15 -o labels.npy

needs gudhi (pip install "knnrefine[topology]"). Without --n-clusters the number is chosen at
the largest gap between the peaks' prominences. Outputs: .csv (x, y, label) or .npy (labels)"""


def add_arguments(parser):
    add_input_options(parser)
    add_refine_options(parser, k_required=False, k_help="which nearest neighbour")
    add_mesh_option(parser)
    parser.add_argument("--n-clusters", type=int, help="how many clusters to keep")
    parser.add_argument("-o", "--output", metavar="FILE", help="write the labels (.csv, .npy)")
    parser.add_argument("--plot", metavar="PICTURE", help="draw the clusters (.png .svg .pdf)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")


def run(args):
    import os

    from .. import io
    from ..cluster import cluster
    from ..errors import InputError
    from ..plot import figure_size, plot_clusters, save_figure
    from .common import require_outputs_free

    require_outputs_free([p for p in (args.output, args.plot) if p], args.force)
    points = io.read_points(args.points, args.columns, args.delimiter)
    mesh, _ = mesh_for(args, points)
    cl = cluster(mesh, points, n_clusters=args.n_clusters)
    if args.output:
        ext = os.path.splitext(args.output)[1].lower()
        if ext == ".csv":
            io.write_table(
                args.output,
                ["x", "y", "label"],
                np.column_stack([points, cl.labels]),
                args.force,
                ["%.17g", "%.17g", "%d"],
            )
        elif ext == ".npy":
            io.atomic_write(args.output, args.force, lambda tmp: np.save(tmp, cl.labels))
        else:
            raise InputError(f"{args.output}: labels are written as .csv or .npy")
    if args.plot:
        labels = tuple(args.columns.split(",")) if args.columns else ("x", "y")
        save_figure(
            args.plot,
            figure_size(mesh),
            lambda ax: plot_clusters(mesh, points, cl.labels, ax, labels_xy=labels),
            force=args.force,
        )
    if not args.quiet:
        sizes = np.bincount(cl.labels)
        prom = ", ".join(f"{p:.3g}" for p in cl.prominence[: cl.n_clusters + 2])
        print(
            f"{cl.n_clusters} clusters of n = {len(points):,} points from m = "
            f"{len(mesh.vertices):,} mesh vertices (k = {mesh.k}) in {cl.seconds:.2f} s"
        )
        print(f"  sizes: {', '.join(str(s) for s in sizes)}; prominences (log density): {prom}")
        written = [p for p in (args.output, args.plot) if p]
        if written:
            print("  wrote " + ", ".join(written))
    return 0
