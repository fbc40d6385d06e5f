"""knnrefine density: the density estimate on a grid, and its picture."""

import os
import time

import numpy as np

from .common import (
    add_input_options,
    add_mesh_option,
    add_random_state_option,
    add_refine_options,
    mesh_for,
)

HELP = "estimate the density (adaptive kernel, or kNN k / (n V_d d_Pk^d)) on a grid"
EXAMPLES = """examples:
  knnrefine density quakes.csv --sphere -k 30 --radius 6371.0088 -o density.npz \\
      --plot density.png
  knnrefine density angles.csv --periodic --box 0 0 360 360 --plot angles-density.png
  knnrefine density counts.csv --columns x,y --weights count -o density.csv
  knnrefine density points.npy --method knn --mesh mesh.npz --grid 1024 -o density.csv
  knnrefine density chi.csv --columns chi1,chi2,chi3 --periodic --box 0 0 0 360 360 360 \\
      -o density.npz --plot projections.png

the density integrates to 1 over the box. --method adaptive (default): one kernel per point,
of extent c G (d_Pk / G)^(d alpha) in d dimensions, c and alpha by leave-one-out likelihood
(or --criterion least-squares) unless given;
-k defaults to 2 sqrt(n). --method knn: k / (n V_d d_Pk^d), -k defaults to sqrt(n) / 2.
Points in space (three --columns, a six-number --box or a --mesh in space) get either
estimate (balls for kernels) on a 64^3 grid by default, drawn as its projections along each
axis.
Outputs: .npz (xs, ys[, zs], density, d_pk on the grid), .csv (x, y[, z], density, d_pk per
grid cell), pictures (.png .svg .pdf)"""


ERROR_TERMS = 4e6  # the report's probes of d_Pk's error, times k (10 s at k = 2000 with 20,000)


def add_arguments(parser):
    add_input_options(parser)
    add_refine_options(
        parser,
        k_help="which nearest neighbour (default 2 sqrt(n) adaptive, sqrt(n) / 2 knn)",
    )
    add_mesh_option(parser)
    add_random_state_option(parser, "the points the smoothing is chosen at")
    parser.add_argument(
        "--method",
        choices=("adaptive", "knn"),
        help="adaptive kernel estimate (default) or the kNN estimate",
    )
    parser.add_argument(
        "--bandwidth",
        type=float,
        metavar="C",
        help="adaptive: the kernels' factor c > 0 (default: by leave-one-out likelihood)",
    )
    parser.add_argument(
        "--sensitivity",
        type=float,
        metavar="ALPHA",
        help="adaptive: kernels ~ f^-alpha, alpha in [0, 1]; 0.5 is Abramson's law, 0 a fixed "
        "bandwidth (default: by leave-one-out likelihood)",
    )
    parser.add_argument(
        "--criterion",
        choices=("likelihood", "least-squares"),
        default="likelihood",
        help="adaptive: what chooses c and alpha when not given: leave-one-out likelihood "
        "(default), or least-squares cross-validation (wider kernels, lower L1 error)",
    )
    parser.add_argument(
        "--shape",
        choices=("isotropic", "local"),
        default="isotropic",
        help="adaptive: disks (balls in space), or ellipses shaped like the points nearby "
        "(thin ridges; the plane only)",
    )
    parser.add_argument(
        "--grid",
        type=int,
        nargs="+",
        metavar="N",
        help="grid cells per axis (one number, or nx ny, or nx ny nz in space; default 512 "
        "in the plane, 64 in space)",
    )
    parser.add_argument(
        "--extent",
        type=float,
        nargs="+",
        metavar="V",
        help="the grid's region: X0 Y0 X1 Y1 (X0 Y0 Z0 X1 Y1 Z1 in space; LON0 LAT0 LON1 LAT1 "
        "in degrees on the sphere); default the box (the whole sphere); NaN beyond the box",
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
    parser.add_argument(
        "--plot-style",
        choices=("hdr", "image"),
        default="hdr",
        help="the plane's picture: filled contours of the regions holding 50, 80 and 95%% of "
        "the mass (default), or an image on a log colour scale",
    )
    parser.add_argument("--force", action="store_true", help="overwrite existing files")


def _check_smoothing(args):
    """The adaptive options, before any work (usage errors, exit 2)."""
    from ..density.adaptive import check_bandwidth, check_sensitivity
    from ..errors import InputError
    from .common import UsageError

    if args.method is None:
        args.method = "adaptive"
    if args.method == "adaptive" and args.dim == 3 and args.shape == "local":
        raise UsageError(
            "--shape local is built for points in the plane; in space the kernels are balls "
            "(--shape isotropic, the default)"
        )
    if args.method == "knn":
        set_ = {
            "--bandwidth": args.bandwidth is not None,
            "--sensitivity": args.sensitivity is not None,
            "--shape": args.shape != "isotropic",
            "--criterion": args.criterion != "likelihood",
        }
        given = [flag for flag, is_set in set_.items() if is_set]
        if given:
            verb = "belongs" if len(given) == 1 else "belong"
            raise UsageError(f"{', '.join(given)} {verb} to --method adaptive, not knn")
        return
    try:
        if args.bandwidth is not None:
            check_bandwidth(args.bandwidth)
        if args.sensitivity is not None:
            check_sensitivity(args.sensitivity)
    except InputError as exc:
        raise UsageError(f"--{exc}") from None


def run(args):
    from .. import io
    from .._validation import check_weights
    from ..density import (
        BANDWIDTHS,
        SENSITIVITIES,
        AdaptiveDensity,
        KnnDensity,
        choose_smoothing,
        default_k,
        default_pilot_k,
    )
    from ..density.adaptive import SphereAdaptiveDensity
    from ..plot import (
        MAP_PROJECTION,
        figure_size,
        plot_density,
        plot_projections,
        save_figure,
        space_figure_size,
    )
    from .common import (
        PICTURES,
        UsageError,
        check_outputs,
        dim_of,
        given_mesh,
        plural,
        space_columns,
        stage_bar,
    )

    if not args.output and not args.plot:
        raise UsageError("nothing to write: give -o FILE and/or --plot PICTURE")
    args.dim = dim = dim_of(args)
    sphere = bool(getattr(args, "sphere", False)) or bool(
        getattr(given_mesh(args), "on_sphere", False)
    )
    args.sphere = sphere
    if sphere and args.shape != "isotropic":
        raise UsageError("--shape local is built for the plane; on the sphere kernels are caps")
    grid = [512 if dim == 2 else 64] if args.grid is None else args.grid
    if sphere and args.grid is None:
        grid = [720, 360]  # half a degree
    if len(grid) not in (1, dim) or min(grid) < 1:
        shapes = "N, or NX NY" if dim == 2 else "N, or NX NY NZ"
        raise UsageError(
            f"--grid takes one or {('two', 'three')[dim - 2]} positive numbers of cells "
            f"({shapes}), got "
            f"{' '.join(map(str, grid))}"
        )
    _check_smoothing(args)
    if args.extent is not None:
        from ..density.distance import check_extent
        from ..errors import InputError

        try:
            args.extent = check_extent(args.extent, dim, sphere)
        except InputError as bad:
            raise UsageError(f"--extent: {bad}") from None
    check_outputs(
        [(p, (".npz", ".csv"), "grids") for p in args.output]
        + ([(args.plot, PICTURES, "pictures")] if args.plot else []),
        args,
    )
    cells = (grid * dim)[:dim]  # nx, ny[, nz]
    points, weights, names = io.read_weighted_points(
        args.points, space_columns(args, dim), args.weights, args.delimiter
    )
    if weights is not None:
        weights = check_weights(weights, len(points))
        points, weights = points[weights > 0], weights[weights > 0]
    adaptive = args.method == "adaptive"
    mesh, _ = mesh_for(args, points, default_pilot_k if adaptive else default_k, weights)
    t0 = time.perf_counter()
    knn = KnnDensity(mesh, points, weights=weights)
    *axes, d = knn.distance.grid(tuple(cells[::-1]), args.extent)
    if adaptive:
        alphas = SENSITIVITIES if args.sensitivity is None else (args.sensitivity,)
        cs = BANDWIDTHS if args.bandwidth is None else (args.bandwidth,)
        if sphere:
            density = SphereAdaptiveDensity(mesh, points, cs[0], alphas[0], weights=weights,
                                            knn=knn)  # fmt: skip
        else:
            density = AdaptiveDensity(
                mesh, points, cs[0], args.shape, weights=weights, knn=knn, sensitivity=alphas[0]
            )
        scored = 0
        if len(alphas) > 1 or len(cs) > 1:
            with stage_bar(args.quiet, "choosing the smoothing", " pairs scored") as update:
                table = choose_smoothing(
                    density, alphas, cs, criterion=args.criterion, progress=update,
                    random_state=args.random_state,
                )[2]  # fmt: skip
            scored = len(table)
        f = density.grid(tuple(cells[::-1]), args.extent)[-1]
    else:
        density = knn
        f = knn.at_distance(d)
    seconds = time.perf_counter() - t0
    n = len(points) if weights is None else float(weights.sum())
    extra = {}
    if adaptive:
        extra = {"bandwidth": density.bandwidth, "sensitivity": density.sensitivity}
        if scored:
            extra["criterion"] = args.criterion
    for path in args.output:
        ext = os.path.splitext(path)[1].lower()
        if ext == ".npz":
            io.atomic_write(
                path,
                args.force,
                lambda tmp: np.savez_compressed(
                    tmp,
                    **dict(zip(("xs", "ys", "zs"), axes, strict=False)),
                    density=f,
                    d_pk=d,
                    k=mesh.k,
                    n=n,
                    box=np.array(mesh.extent),
                    extent=np.array(mesh.extent if args.extent is None else args.extent),
                    periodic=np.array(mesh.periodic),
                    method=args.method,
                    **extra,
                ),
            )
        else:
            # grid order: the last axis (x) fastest, as the arrays are laid out
            at = np.meshgrid(*axes[::-1], indexing="ij")[::-1]
            io.write_table(
                path,
                {
                    **{name: at[a].ravel() for a, name in enumerate(names)},
                    "density": f.ravel(),
                    "d_pk": d.ravel(),
                },
                force=args.force,
            )
    if args.plot and dim == 3:  # projections along each axis, with the points
        save_figure(
            args.plot,
            space_figure_size(),
            lambda axs: plot_projections(density, axs, grid=(*axes, f), points=points),
            force=args.force,
            panels=3,
        )
    elif args.plot:
        save_figure(
            args.plot,
            (10.0, 5.6) if sphere else figure_size(mesh),
            lambda ax: plot_density(
                density, ax, labels=names, grid=(*axes, f), style=args.plot_style
            ),
            force=args.force,
            projection=MAP_PROJECTION if sphere else None,
        )
    if not args.quiet:
        # exact d_Pk costs about k per probe: at most ERROR_TERMS neighbours in all
        err = knn.distance.error(n_random=int(np.clip(ERROR_TERMS / mesh.k, 500, 20000)))
        what = "adaptive kernel density" if adaptive else "kNN density"
        print(
            f"{what} of n = {plural(n, 'point')}, k = {mesh.k}, on a "
            f"{' x '.join(map(str, cells))} grid from "
            f"m = {plural(len(mesh.vertices), 'mesh vertex', 'mesh vertices')} in {seconds:.2f} s"
        )
        if adaptive:
            by = {"likelihood": "leave-one-out likelihood", "least-squares": "least squares"}
            how = f" (by {by[args.criterion]}, {scored} pairs scored)" if scored else ""
            print(
                f"  kernels: {args.shape}, bandwidth c = {density.bandwidth:.3g}, sensitivity "
                f"alpha = {density.sensitivity:.2g}{how}"
            )
        print(
            f"  d_Pk interpolated from exact values at {len(knn.distance.values):,} nodes: "
            f"relative error median {err['median']:.4f}, worst {err['worst']:.3f} "
            f"({err['probes']:,} probes)"
        )
        print("  wrote " + ", ".join(args.output + ([args.plot] if args.plot else [])))
    return 0
