"""knnrefine demo: the whole job on a shipped real data set, into a folder."""

import json
import os
import time

HELP = "refine, draw and certify the shipped Trp chi1/chi2 torsion angles (periodic)"
EXAMPLES = """examples:
  knnrefine demo
  knnrefine demo --out /tmp/demo -k 50

writes mesh.npz, mesh.vtu, mesh.png, certificate.txt and certificate.json into the folder
(default ./knnrefine-demo), then refines and certifies the shipped earthquakes on the sphere
(earth.npz), replacing what an earlier demo put there, and the example inputs
the README's commands use: angles.csv (chi1,chi2; CC BY 4.0), quakes.csv (lon,lat; MIT),
ring.csv and blobs.csv (synthetic)"""

EARTH_KM = 6371.0088  # the mean Earth radius (IUGG), for lengths in kilometres
DATA = (
    "Tryptophan side-chain torsion angles (chi1, chi2) of the Top8000 protein set, "
    "Richardson Lab (CC BY 4.0; Williams et al. 2018, Protein Science 27, 293-315)"
)


def add_arguments(parser):
    parser.add_argument(
        "--out",
        default="knnrefine-demo",
        metavar="DIR",
        help="output folder (default ./knnrefine-demo)",
    )
    parser.add_argument("-k", type=int, default=20, help="which nearest neighbour (default 20)")
    parser.add_argument("--tau", type=float, default=3.0, help="well-spacedness (default 3)")


def run(args):
    from .. import certify, datasets, io, refine
    from .._engine import shipped
    from ..plot import save_plot

    say = (lambda *a: None) if args.quiet else print
    points = datasets.trp_chi1_chi2()
    say(f"knnrefine demo: {len(points):,} points on the 360 x 360 degree torus")
    say(f"  data: {DATA}")
    t0 = time.perf_counter()
    refine(points[:500], 5, args.tau, periodic=True, box=datasets.TRP_BOX)
    warm = time.perf_counter() - t0  # compiles the kernels on first use, then loads them
    how = ("compiled when the package was built" if shipped.in_use()
           else "compiled on first use, cached afterwards")  # fmt: skip
    t0 = time.perf_counter()
    mesh = refine(points, args.k, args.tau, periodic=True, box=datasets.TRP_BOX)
    seconds = time.perf_counter() - t0
    moves = mesh.stats["moves"]
    say(
        f"  refined with k = {mesh.k}, tau = {mesh.tau:g}: m = {len(mesh.vertices):,} vertices, "
        f"{len(mesh.triangles):,} triangles ({moves['break_circumball']} circumball breaks, "
        f"{moves['break_cell']} cell breaks, {moves['clean']} cleans) in {seconds:.2f} s "
        f"(kernels ready in {warm:.1f} s: {how})"
    )
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        from ..errors import InputError

        raise InputError(f"--out {args.out}: exists and is not a folder")
    os.makedirs(args.out, exist_ok=True)
    files = {
        name: os.path.join(args.out, name)
        for name in ("mesh.npz", "mesh.vtu", "mesh.png", "certificate.txt", "certificate.json")
    }
    examples = {
        "angles.csv": (points, ("chi1", "chi2")),
        "quakes.csv": (datasets.earthquakes(), ("lon", "lat")),
        "ring.csv": (datasets.ring(), ("x", "y")),
        "blobs.csv": (datasets.blobs(), ("x", "y")),
    }
    for name, (table, (a, b)) in examples.items():
        io.write_table(os.path.join(args.out, name), {a: table[:, 0], b: table[:, 1]}, force=True)
    io.write_mesh(mesh, files["mesh.npz"], force=True)
    io.write_mesh(mesh, files["mesh.vtu"], force=True)
    save_plot(
        mesh,
        files["mesh.png"],
        points=points,
        force=True,
        labels=("chi1 (degrees)", "chi2 (degrees)"),
    )
    cert = certify(mesh, points)
    text = str(cert) + "\n"
    io.write_text(files["certificate.txt"], text, force=True)
    blob = json.dumps(cert.to_dict(), indent=1)
    io.write_text(files["certificate.json"], blob, force=True)
    say(
        f"  certified in {cert.seconds:.2f} s: d_M2 / d_Pk in [{cert.alpha_hat:.3f}, "
        f"{cert.beta_hat:.3f}] (Theorem 6 allows [{cert.alpha:.4f}, {cert.beta:.2f}]), "
        f"max aspect {cert.max_aspect:.3f}: {'PASSED' if cert.passed else 'FAILED'}"
    )
    quakes = examples["quakes.csv"][0]
    world = refine(quakes, 30, args.tau, sphere=True, radius=EARTH_KM)
    files["earth.npz"] = os.path.join(args.out, "earth.npz")
    io.write_mesh(world, files["earth.npz"], force=True)
    round_earth = certify(world, quakes)
    say(
        f"  on the sphere: the {len(quakes):,} earthquakes (k = 30, great-circle km) into "
        f"m = {len(world.vertices):,} vertices in {world.stats.seconds:.2f} s, certified: "
        f"d_M2 / d_Pk in [{round_earth.alpha_hat:.3f}, {round_earth.beta_hat:.3f}]: "
        f"{'PASSED' if round_earth.passed else 'FAILED'}"
    )
    say(f"  wrote {', '.join(files.values())}")
    say(f"  example inputs for the README's commands: {', '.join(examples)} (in {args.out})")
    say("  next: open mesh.vtu in ParaView, or try 'knnrefine refine --help'")
    return 0 if cert.passed and round_earth.passed else 3
