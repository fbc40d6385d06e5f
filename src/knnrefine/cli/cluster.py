"""knnrefine cluster: ToMATo clusters of the points through the mesh."""

import numpy as np

from .common import add_input_options, add_mesh_option, add_refine_options, mesh_for

HELP = "cluster the points by the modes of their kNN density (ToMATo on the mesh)"
EXAMPLES = """examples:
  knnrefine cluster blobs.csv -k 50 --noise -o labels.csv --plot clusters.png
  knnrefine cluster points.npy --mesh mesh.npz --n-clusters 15 -o labels.npy
  knnrefine cluster chi.csv --columns chi1,chi2,chi3 --periodic --box 0 0 0 360 360 360 \\
      -k 30 -o labels.csv --plot views.png

needs gudhi (pip install "knnrefine[topology]"). Without --n-clusters the clusters are the
density peaks whose prominence exceeds T = 2 sqrt(ln(n/k) / k), the largest a flat density
gives by chance; --noise labels -1 the points not significantly above where their cluster
meets another. Points in space (three --columns, a six-number --box or a --mesh in space)
are drawn in three views. Outputs: .csv (row, the columns, label) or .npy (labels)"""


def add_arguments(parser):
    add_input_options(parser)
    add_refine_options(parser)
    add_mesh_option(parser)
    parser.add_argument("--n-clusters", type=int, help="how many clusters to keep")
    parser.add_argument("--noise", action="store_true", help="label -1 the points between clusters")
    parser.add_argument("-o", "--output", metavar="FILE", help="write the labels (.csv, .npy)")
    parser.add_argument("--plot", metavar="PICTURE", help="draw the clusters (.png .svg .pdf)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")


def run(args):
    import os

    from .. import io
    from .._validation import default_k
    from ..cluster import cluster
    from ..plot import (
        MAP_PROJECTION,
        figure_size,
        plot_clusters,
        plot_clusters_projected,
        save_figure,
        space_figure_size,
    )
    from ..topology import require_gudhi
    from .common import PICTURES, check_outputs, dim_of, plural, read_input

    outputs = [(args.output, (".csv", ".npy"), "labels")] if args.output else []
    outputs += [(args.plot, PICTURES, "pictures")] if args.plot else []
    check_outputs(outputs, args)
    require_gudhi()
    points, weights, names = read_input(args, dim=dim_of(args))
    mesh, _ = mesh_for(args, points, default_k, weights)
    cl = cluster(mesh, points, n_clusters=args.n_clusters, noise=args.noise, weights=weights)
    if args.output:
        if os.path.splitext(args.output)[1].lower() == ".csv":
            io.write_table(
                args.output,
                {
                    "row": np.arange(len(points)),
                    **{name: points[:, a] for a, name in enumerate(names)},
                    "label": cl.labels,
                },
                force=args.force,
            )
        else:
            io.atomic_write(args.output, args.force, lambda tmp: np.save(tmp, cl.labels))
    if args.plot and mesh.dim == 3:  # the three views of the box
        save_figure(
            args.plot,
            space_figure_size(),
            lambda axes: plot_clusters_projected(mesh, points, cl.labels, axes),
            force=args.force,
            panels=3,
        )
    elif args.plot:
        save_figure(
            args.plot,
            (11.0, 5.6) if mesh.on_sphere else figure_size(mesh),
            lambda ax: plot_clusters(mesh, points, cl.labels, ax, labels_xy=names),
            force=args.force,
            projection=MAP_PROJECTION if mesh.on_sphere else None,
        )
    if not args.quiet:
        sizes = np.bincount(cl.labels[cl.labels >= 0], minlength=cl.n_clusters)
        prom = _first(cl.prominence[: cl.n_clusters + 2], "{:.3g}")
        print(
            f"{plural(cl.n_clusters, 'cluster')} of n = {plural(len(points), 'point')} from "
            f"m = {plural(len(mesh.vertices), 'mesh vertex', 'mesh vertices')} (k = {mesh.k}) "
            f"in {cl.seconds:.2f} s"
        )
        noise = f"; noise: {plural(cl.noise, 'point')}" if args.noise else ""
        print(
            f"  sizes: {_first(sizes, '{:,}')}{noise}; prominences (ln density): "
            f"{prom}; significance threshold {cl.threshold:.3g}"
        )
        written = [p for p in (args.output, args.plot) if p]
        if written:
            print("  wrote " + ", ".join(written))
    return 0


SHOWN = 10  # numbers a summary line shows before it says how many more there are


def _first(values, form):
    """The first SHOWN of ``values`` formatted, and how many more there are: one line
    however many clusters a run finds."""
    shown = ", ".join(form.format(v) for v in values[:SHOWN])
    more = len(values) - SHOWN
    return shown + (f" and {more:,} more" if more > 0 else "")
