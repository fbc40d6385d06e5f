"""Options and helpers shared by the subcommands."""

import argparse
import contextlib
import os
import sys
import time
import warnings

from .._options import ProgressBar
from ..errors import InputError, KnnRefineError

PICTURES = (".png", ".svg", ".pdf")
MESHES = (".npz", ".vtu", ".vtk", ".xdmf", ".geojson", ".csv")


class UsageError(KnnRefineError):
    """The command line itself is wrong (a missing or malformed option): exit status 2."""


def plural(count, word, words=None):
    """'1 point', '2 points', '2.5 points' (with thousands separators; a whole total of
    weights as a whole number)."""
    if float(count).is_integer():
        count = int(count)
    return f"{count:,} {word if count == 1 else (words or word + 's')}"


def check_outputs(outputs, args):
    """Every output, before any work: its extension, its folder (exists, writable), not a
    folder, not one of the command's inputs (its points, its mesh: whatever --force says),
    and no existing file unless --force. ``outputs``: [(path, allowed extensions, what),
    ...]; ``args``: the command's (--force and its input files)."""
    force = args.force
    inputs = [p for p in (getattr(args, "points", None), getattr(args, "mesh", None))
              if isinstance(p, str) and p != "-" and os.path.exists(p)]  # fmt: skip
    seen = set()
    for path, allowed, what in outputs:
        ext = os.path.splitext(path)[1].lower()
        if ext not in allowed:
            raise InputError(f"{path}: {what} are written as {', '.join(allowed)}")
        full = os.path.abspath(path)
        if full in seen:
            raise InputError(f"{path} is given twice as an output")
        seen.add(full)
        if os.path.isdir(path):
            raise InputError(f"{path} is a folder: give a file name")
        for source in inputs:
            if os.path.exists(path) and os.path.samefile(path, source):
                raise InputError(
                    f"{path} is this command's input {source}: write the output to another "
                    "file (--force never overwrites an input)"
                )
        folder = os.path.dirname(full)
        if not os.path.isdir(folder):
            raise InputError(f"{path}: the folder {os.path.dirname(path) or '.'} does not exist")
        if not os.access(folder, os.W_OK):
            raise InputError(f"{path}: the folder {os.path.dirname(path) or '.'} is not writable")
        if os.path.exists(path) and not force:
            raise InputError(f"{path} exists; use --force to overwrite it")


def read_input(args, path=None, dim=None):
    """(points, weights or None, the columns' names) from the command's input options: the
    columns' names for axes and output headers come from --columns or the file's header,
    else x, y (and z); the weights from --weights. Three columns (the first three unless
    --columns names them) for points in space: three --columns, a six-number --box, or
    ``dim`` = 3 (a mesh in space)."""
    from .. import io

    return io.read_weighted_points(
        path or args.points, space_columns(args, dim), getattr(args, "weights", None),
        args.delimiter,
    )  # fmt: skip


def space_columns(args, dim=None):
    """--columns as given, the first three columns for points in space (see
    ``read_input``), or on the sphere the longitude and latitude columns found by name."""
    if args.columns is None and getattr(args, "sphere", False):
        from ..io import LONLAT

        return LONLAT
    if args.columns is None and (dim == 3 or in_space(args)):
        return "0,1,2"
    return args.columns


def add_input_options(parser, positional="points"):
    parser.add_argument(
        positional, help="points: CSV/TSV/text, .npy, .npz, .parquet, or - for standard input"
    )
    parser.add_argument(
        "--weights",
        metavar="COLUMN",
        help="a column of weights >= 0 (counts, survey weights), by name or index; "
        "a point of weight w counts as w points (as refine's weights=)",
    )
    parser.add_argument(
        "--columns",
        metavar="A,B[,C]",
        help="the x and y columns, by name (lon,lat) or zero-based index (2,3); "
        "three columns (x,y,z) for points in space; default: the first two (three with a "
        "six-number --box or a mesh in space)",
    )
    parser.add_argument(
        "--delimiter",
        metavar="D",
        help="text field separator; default: sniffed (comma, tab, semicolon or whitespace)",
    )


def number(text):
    """-k as refine takes it: a whole number, or any positive number with --weights."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    return int(value) if value.is_integer() else value


def add_refine_options(
    parser,
    k_help="which nearest neighbour, k >= 1 (any number up to the total weight with "
    "--weights; default sqrt(n) / 2, at least 10)",
):
    parser.add_argument("-k", type=number, help=k_help)
    parser.add_argument("--tau", type=float, default=3.0, help="well-spacedness, > 2 (default 3)")
    parser.add_argument(
        "--periodic", action="store_true", help="the box is a flat torus (needs --box)"
    )
    for axis in "xyz":
        parser.add_argument(
            f"--periodic-{axis}",
            action="store_true",
            help=f"periodic in {axis} (any of --periodic-x/y/z together"
            + (", points in space)" if axis == "z" else ")"),
        )
    add_workers_option(parser)
    parser.add_argument(
        "--box",
        type=float,
        nargs="+",
        metavar="BOUND",
        help="the box: XMIN YMIN XMAX YMAX, or XMIN YMIN ZMIN XMAX YMAX ZMAX for points in "
        "space; default: the points' bounding box",
    )
    parser.add_argument(
        "--sphere",
        action="store_true",
        help="the points are longitude and latitude in degrees on the sphere (columns found "
        "by name: lon/lng/longitude, lat/latitude; else --columns); great-circle distances, "
        "no --box or --periodic",
    )
    parser.add_argument(
        "--radius",
        type=float,
        help="with --sphere, the sphere's radius in the length unit wanted (6371.0088 for "
        "kilometres on the Earth); default 1 (radians)",
    )
    parser.add_argument(
        "--min-size",
        type=float,
        help="resolution floor (default 1e-6 of the box's longer side; on the sphere 1e-6 pi "
        "radians)",
    )
    parser.add_argument("--max-vertices", type=int, help="vertex budget")

    parser.add_argument(
        "--time-limit", type=float, metavar="SECONDS", help="time budget for the refinement"
    )


def add_workers_option(parser):
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="threads of this process (as refine's and certify's workers=; default: one run "
        "whose kernels use every core)",
    )


def add_random_state_option(parser, what):
    parser.add_argument(
        "--random-state",
        type=int,
        default=0,
        metavar="SEED",
        help=f"the seed of {what} (as the API's random_state=; default 0)",
    )


def in_space(args):
    """Whether the command reads points in space: three --columns or a six-number --box."""
    columns = getattr(args, "columns", None)
    box = getattr(args, "box", None)
    return (columns is not None and len(str(columns).split(",")) == 3) or (
        box is not None and len(box) == 6
    )


def periodic_of(args):
    """The --periodic flags as refine's ``periodic``: a bool, or one bool per axis."""
    box = getattr(args, "box", None)
    if getattr(args, "sphere", False):
        if box is not None or args.periodic or args.periodic_x or args.periodic_y or getattr(
            args, "periodic_z", False
        ):  # fmt: skip
            raise UsageError("--sphere takes no --box or --periodic: the sphere has neither")
        return False
    if getattr(args, "radius", None) is not None:
        raise UsageError("--radius is the sphere's: give it with --sphere")
    if box is not None and len(box) not in (4, 6):
        raise UsageError(
            f"--box takes 4 numbers (XMIN YMIN XMAX YMAX) or 6 for points in space "
            f"(XMIN YMIN ZMIN XMAX YMAX ZMAX), got {len(box)}"
        )
    z = getattr(args, "periodic_z", False)
    flags = {"--periodic-x": args.periodic_x, "--periodic-y": args.periodic_y, "--periodic-z": z}
    named = [flag for flag, on in flags.items() if on]
    if box is None and (args.periodic or named):
        flag = "--periodic" if args.periodic else named[0]
        raise UsageError(
            f"{flag} needs --box XMIN YMIN XMAX YMAX (XMIN YMIN ZMIN XMAX YMAX ZMAX in space): "
            "the periods are its sides (for angles in degrees, e.g. --box -180 -180 180 180)"
        )
    if args.periodic:
        return True
    if not named:
        return False
    dim = 3 if in_space(args) else 2
    if z and dim == 2:
        raise UsageError("--periodic-z is for points in space (three --columns)")
    return tuple(flags[f"--periodic-{'xyz'[a]}"] for a in range(dim))


def announce_compilation(quiet, domain="plane"):
    """Say so when the kernels of ``domain`` ("plane", "space" or "sphere") are about to be
    compiled (the first run: 10-60 s, once)."""
    from .._engine.jit import is_ready

    if domain == "sphere":
        from .._engine.refine_sphere import refine_steps_sphere as steps
    elif domain == "space":
        from .._engine.refine3 import refine_steps3 as steps
    else:
        from .._engine.refine import refine_steps as steps

    if not quiet and not is_ready(steps):
        print(
            "knnrefine: compiling the kernels for their first use (10-60 s, once; later runs "
            "load them from the cache)",
            file=sys.stderr,
            flush=True,
        )


@contextlib.contextmanager
def stage_bar(quiet, desc, unit):
    """A progress bar for one stage of long work (shown only after a second, and only on a
    terminal, unless quiet): yields update(count), the count done so far."""
    bar = None
    if not quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=None, unit=unit, delay=1.0, desc=desc, leave=False, dynamic_ncols=True)

    def update(count):
        if bar is not None:
            bar.update(count - bar.n)

    try:
        yield update
    finally:
        if bar is not None:
            bar.close()


def refine_with_progress(points, args, quiet, weights=None, start=None):
    """knnrefine.refine with a progress bar (shown only after a second, and only on a
    terminal) unless quiet; ``start``: the mesh it continues."""
    from .. import refine

    shape = getattr(points, "shape", ())
    if getattr(args, "sphere", False):
        domain = "sphere"
    else:
        domain = "space" if len(shape) == 2 and shape[1] == 3 else "plane"
    announce_compilation(quiet, domain)
    # a bar only on a terminal: no carriage returns in a redirected stderr
    bar = ProgressBar() if not quiet and sys.stderr.isatty() else None
    t0 = time.perf_counter()
    caught = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sphere = (
                {"sphere": True, "radius": args.radius} if getattr(args, "sphere", False) else {}
            )
            mesh = refine(
                points,
                args.k,
                args.tau,
                **sphere,
                periodic=periodic_of(args),
                box=tuple(args.box) if args.box else None,
                min_size=args.min_size,
                max_vertices=args.max_vertices,
                time_limit=args.time_limit,
                progress=bar,
                weights=weights,
                workers=getattr(args, "workers", None),
                start=start,
            )
    finally:
        if bar is not None:
            bar.close()
        for w in caught:  # after the bar is gone, so that the two do not interleave
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return mesh, time.perf_counter() - t0


def summary(mesh, seconds):
    """The refine command's report, the same lines in every domain (one stats record)."""
    st = mesh.stats
    t, moves = st.time, st.moves
    cells = "tetrahedra" if mesh.dim == 3 and not mesh.on_sphere else "triangles"
    where = {True: " on the sphere", False: " in space" if mesh.dim == 3 else ""}[mesh.on_sphere]
    unit = ""
    if mesh.on_sphere:
        unit = ", radians" if mesh.radius == 1.0 else f", radius {mesh.radius:g}"
    ball = "circumcap" if mesh.on_sphere else "circumball"
    floor = st.floor_circumballs + st.floor_cells
    lines = [
        f"refined n = {st.n:,} points{where} (k = {mesh.k}, tau = {mesh.tau:g}{unit}) into "
        f"m = {len(mesh.vertices):,} vertices and {len(mesh.cells):,} {cells} in "
        f"{seconds:.2f} s (setup {t.get('setup', 0.0):.2f} s, refinement "
        f"{t.get('refine', 0.0):.2f} s)",
        f"  moves: {moves['break_circumball']:,} {ball} breaks, {moves['break_cell']:,} "
        f"cell breaks, {moves['clean']:,} cleans; Theorem 6: alpha = {mesh.alpha:.4f}, "
        f"beta = {mesh.beta:.2f}",
    ]
    if floor:
        lines.append(
            f"  resolution floor reached by {floor} elements "
            f"(min_size = {mesh.min_size:.3g}); see 'knnrefine certify'"
        )
    return "\n".join(lines)


def add_mesh_option(parser):
    parser.add_argument(
        "--mesh",
        metavar="MESH.npz",
        help="use this mesh (from 'knnrefine refine', made from the same points) "
        "instead of refining again; its k is used",
    )


def given_mesh(args):
    """The mesh of --mesh (read once), or None."""
    from .. import io

    if not getattr(args, "mesh", None):
        return None
    if getattr(args, "_given_mesh", None) is None:
        args._given_mesh = io.read_mesh(args.mesh)
    return args._given_mesh


def dim_of(args):
    """3 for points in space (a mesh in space from --mesh, three --columns or a six-number
    --box), else 2."""
    mesh = given_mesh(args)
    if mesh is not None:
        return mesh.dim
    return 3 if in_space(args) else 2


def mesh_for(args, points, default_k=None, weights=None):
    """The mesh of the points: --mesh if given, else a refinement with the options (counting
    ``weights``; default_k of their total)."""
    if args.mesh:
        mesh = given_mesh(args)
        if args.k is not None and args.k != mesh.k:
            raise InputError(f"-k {args.k} disagrees with the mesh's k = {mesh.k}")
        return mesh, 0.0
    if args.k is None:
        if default_k is None:
            raise UsageError("the following argument is required: -k (or --mesh MESH.npz)")
        args.k = default_k(len(points) if weights is None else float(weights.sum()))
    return refine_with_progress(points, args, args.quiet, weights)
