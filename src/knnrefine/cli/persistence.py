"""knnrefine persistence: the persistence diagram of the sublevel sets of d_Pk."""

import numpy as np

from .common import add_input_options, add_mesh_option, add_refine_options, mesh_for

HELP = "persistent homology of the sublevel sets of d_Pk (robust to outliers)"
EXAMPLES = """examples:
  knnrefine persistence ring.csv -k 30 -o diagram.csv --plot diagram.png
  knnrefine persistence angles.csv -k 50 --periodic --box 0 0 360 360 --linear
  knnrefine persistence chi.csv --columns chi1,chi2,chi3 --periodic \\
      --box 0 0 0 360 360 360 -k 20 -o diagram.csv

needs gudhi (pip install "knnrefine[topology]"). The diagram is in ln d_Pk (natural log) unless
--linear; the CSV has one row per class: dimension, birth, death (inf: never dies). Points in
space (three --columns, a six-number --box or a --mesh in space) give classes H0-H3"""


def add_arguments(parser):
    add_input_options(parser)
    add_refine_options(parser)
    add_mesh_option(parser)
    parser.add_argument("--linear", action="store_true", help="d_Pk itself, not its logarithm")
    parser.add_argument("-o", "--output", metavar="FILE", help="write the diagram (.csv)")
    parser.add_argument("--plot", metavar="PICTURE", help="draw the diagram (.png .svg .pdf)")
    parser.add_argument("--top", type=int, default=5, help="classes listed per dimension")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")


def run(args):
    from .. import io
    from .._validation import default_k
    from ..plot import plot_diagram, save_figure
    from ..topology import Persistence, require_gudhi
    from .common import PICTURES, check_outputs, dim_of, plural, read_input

    outputs = [(args.output, (".csv",), "diagrams")] if args.output else []
    outputs += [(args.plot, PICTURES, "pictures")] if args.plot else []
    check_outputs(outputs, args)
    require_gudhi()
    points, weights, _ = read_input(args, dim=dim_of(args))
    mesh, _ = mesh_for(args, points, default_k, weights)
    ph = Persistence(mesh, points, log=not args.linear, weights=weights)
    dims = tuple(range(mesh.dim + 1))  # classes up to the top dimension: H0-H2, or H0-H3
    if args.output:
        rows = np.concatenate(
            [np.column_stack([np.full(len(ph.diagram(d)), d), ph.diagram(d)]) for d in dims]
        )
        io.write_table(
            args.output,
            {"dimension": rows[:, 0].astype(int), "birth": rows[:, 1], "death": rows[:, 2]},
            force=args.force,
        )
    if args.plot:
        save_figure(
            args.plot, (6.5, 6), lambda ax: plot_diagram(ph, ax, dims=dims), force=args.force
        )
    if not args.quiet:
        scale = "ln d_Pk" if ph.log else "d_Pk"
        cell, cells = ("triangle", "triangles") if mesh.dim == 2 else ("tetrahedron", "tetrahedra")
        print(
            f"persistence of the sublevel sets of {scale}: k = {mesh.k}, "
            f"{plural(len(ph.positions), 'node')}, {plural(len(ph.cells), cell, cells)}"
        )
        for d in dims:
            dg = ph.diagram(d)
            life = dg[:, 1] - dg[:, 0]
            order = np.argsort(-life)[: args.top]
            shown = ", ".join(f"[{dg[i, 0]:.4g}, {dg[i, 1]:.4g})" for i in order)
            most = f"; most persistent: {shown}" if len(dg) else ""
            print(f"  H{d}: {plural(len(dg), 'class', 'classes')}{most}")
        written = [p for p in (args.output, args.plot) if p]
        if written:
            print("  wrote " + ", ".join(written))
    return 0
