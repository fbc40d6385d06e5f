"""knnrefine plot: draw a mesh file, with its points if given."""

HELP = "draw a mesh (.npz) as a picture (.png, .svg, .pdf)"
EXAMPLES = """examples:
  knnrefine plot angles.npz -o angles.png --points angles.csv
  knnrefine plot world.npz -o world.png
  knnrefine plot angles.npz -o cells.pdf --cells voronoi --no-mesh
  knnrefine plot chi.npz -o slices.png --points chi.csv --columns chi1,chi2,chi3

a mesh in space is drawn as three slices through the box's centre (one per pair of axes),
coloured by d_M2 (log scale), with the points near each slice as dots"""


def add_arguments(parser):
    parser.add_argument("mesh", help="a mesh written by 'knnrefine refine' (.npz)")
    parser.add_argument(
        "-o", "--output", required=True, metavar="PICTURE", help="the picture: .png, .svg or .pdf"
    )
    parser.add_argument("--points", help="the input points, drawn as dots")
    parser.add_argument(
        "--columns", metavar="A,B[,C]", help="columns of --points (names or indices)"
    )
    parser.add_argument("--delimiter", metavar="D", help="text field separator of --points")
    parser.add_argument(
        "--cells",
        choices=["triangles", "voronoi", "none"],
        default="triangles",
        help="what to colour by d_M2 (default: triangles)",
    )
    parser.add_argument("--no-mesh", action="store_true", help="do not draw the edges")
    parser.add_argument("--force", action="store_true", help="overwrite an existing picture")


def run(args):
    from .. import io
    from ..plot import save_plot
    from .common import PICTURES, UsageError, check_outputs, read_input

    check_outputs([(args.output, PICTURES, "pictures")], args)
    mesh = io.read_mesh(args.mesh)
    if mesh.dim == 3 and (args.cells != "triangles" or args.no_mesh):
        raise UsageError(
            "--cells and --no-mesh draw planar meshes; a mesh in space is drawn as slices "
            "coloured by d_M2"
        )
    points, _, labels = read_input(args, args.points, mesh.dim) if args.points else (None,) * 3
    if mesh.dim == 3:
        from ..plot import save_slices

        save_slices(mesh, args.output, points=points, force=args.force)
        if not args.quiet:
            print(f"wrote {args.output}")
        return 0
    save_plot(
        mesh,
        args.output,
        points=points,
        force=args.force,
        cells=args.cells,
        show_mesh=not args.no_mesh,
        labels=labels or ("x", "y"),
    )
    if not args.quiet:
        print(f"wrote {args.output}")
    return 0
