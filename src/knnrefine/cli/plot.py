"""knnrefine plot: draw a mesh file, with its points if given."""

HELP = "draw a mesh (.npz) as a picture (.png, .svg, .pdf)"
EXAMPLES = """examples:
  knnrefine plot quakes.npz -o quakes.png --points quakes.csv --columns lon,lat
  knnrefine plot angles.npz -o cells.pdf --cells voronoi --no-mesh"""


def add_arguments(parser):
    parser.add_argument("mesh", help="a mesh written by 'knnrefine refine' (.npz)")
    parser.add_argument(
        "-o", "--output", required=True, metavar="PICTURE", help="the picture: .png, .svg or .pdf"
    )
    parser.add_argument("--points", help="the input points, drawn as dots")
    parser.add_argument("--columns", metavar="A,B", help="columns of --points (names or indices)")
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
    from .common import PICTURES, check_outputs, read_input

    check_outputs([(args.output, PICTURES, "pictures")], args.force)
    mesh = io.read_mesh(args.mesh)
    points, labels = read_input(args, args.points) if args.points else (None, ("x", "y"))
    save_plot(
        mesh,
        args.output,
        points=points,
        force=args.force,
        cells=args.cells,
        show_mesh=not args.no_mesh,
        labels=labels,
    )
    if not args.quiet:
        print(f"wrote {args.output}")
    return 0
