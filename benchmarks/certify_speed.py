"""certify beside the refine that made the mesh, in every domain (issue 52's cases).

    python benchmarks/certify_speed.py                  # every case, medians of 3
    python benchmarks/certify_speed.py --repeats 5 --cases plane-uniform-k10 sphere-k100
    python benchmarks/certify_speed.py --quick          # sizes / 10, for a smoke run

Each case runs in a process of its own (so that what one case left in the heap does not
move the next one's memory figures): points drawn once (seeded), one warm-up refine +
certify (kernels compiled and loaded), then ``repeats`` rounds of refine then certify of
that mesh, alternating; the table gives the medians, the ratio certify / refine, each one's
working memory (the peak resident memory above what the process held when the call began,
after the heap was trimmed: ``bench_refine``'s measure; Linux), and certify's probes. The
earthquakes (``../shared/data``, on the sphere) run when the file is there and are skipped
otherwise. Times move 30% run to run on a shared 2-core machine; the ratio is the figure.
"""

import argparse
import os
import statistics
import subprocess
import sys
import time
import warnings

import numpy as np

import knnrefine

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_refine import _status_mb, _trim, reset_peak  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
QUAKES = os.path.join(HERE, "..", "..", "shared", "data", "earthquakes_global_1965_2016.csv")


def _lonlat(n, rng):
    return np.column_stack([rng.uniform(-180, 180, n),
                            np.degrees(np.arcsin(rng.uniform(-1, 1, n)))])  # fmt: skip


def _clustered(n, dim, rng, clusters=2000, spread=0.01):
    centres = rng.random((clusters, dim))
    return np.mod(centres[rng.integers(0, clusters, n)] + rng.normal(0, spread, (n, dim)), 1.0)


def cases(scale):
    """{name: (points, refine's keywords, certify's keywords)}, sizes times ``scale``."""
    rng = np.random.default_rng(52)
    n6, n5 = int(10**6 * scale), int(10**5 * scale)
    out = {}
    uniform = rng.random((n6, 2))
    out["plane-uniform-k10"] = (uniform, dict(k=10, periodic=True, box=(0, 0, 1, 1)), {})
    out["plane-uniform-k100"] = (uniform, dict(k=100, box=(0, 0, 1, 1)), {})
    weights = rng.random(n5 * 2)
    out["plane-weighted-k10"] = (
        rng.random((n5 * 2, 2)), dict(k=10.0, box=(0, 0, 1, 1), weights=weights),
        dict(weights=weights),
    )  # fmt: skip
    mostly_zero = np.where(rng.random(n5 * 2) < 0.95, 0.0, 1.0)
    out["plane-mostly-zero-weights"] = (
        rng.random((n5 * 2, 2)), dict(k=10.0, box=(0, 0, 1, 1), weights=mostly_zero),
        dict(weights=mostly_zero),
    )  # fmt: skip
    out["plane-k1"] = (
        rng.random((n5 // 5, 2)), dict(k=1, box=(0, 0, 1, 1), min_size=1e-3), {}
    )  # fmt: skip
    out["space-clustered-periodic-k10"] = (
        _clustered(n5, 3, rng), dict(k=10, periodic=True, box=(0, 0, 0, 1, 1, 1)), {}
    )  # fmt: skip
    out["space-clustered-box-k10"] = (
        _clustered(n5, 3, rng), dict(k=10, box=(0, 0, 0, 1, 1, 1)), {}
    )  # fmt: skip
    out["sphere-k10"] = (_lonlat(n6 // 2, rng), dict(k=10, sphere=True), {})
    out["sphere-k100"] = (_lonlat(int(144_563 * scale), rng), dict(k=100, sphere=True), {})
    if os.path.exists(QUAKES):
        quakes = np.loadtxt(QUAKES, delimiter=",", skiprows=1)
        out["sphere-earthquakes-k100"] = (quakes, dict(k=100, sphere=True), {})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cases", nargs="*", help="names to run (default: all)")
    ap.add_argument("--quick", action="store_true", help="sizes / 10")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # (the case a child process runs)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")  # k = 1's floor warning: expected, and said here
    scale = 0.1 if args.quick else 1.0
    if args.one:
        _run_case(args.one, *cases(scale)[args.one], args.repeats)
        return
    print(f"machine: {os.cpu_count()} cores; medians of {args.repeats}, warm, a process a case\n")
    print("| case | n | m | refine | certify | certify / refine | memory: refine, certify "
          "| probes | passed |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|", flush=True)
    for name in cases(scale):
        if args.cases and name not in args.cases:
            continue
        child = [sys.executable, os.path.abspath(__file__), "--one", name,
                 "--repeats", str(args.repeats)] + (["--quick"] if args.quick else [])  # fmt: skip
        subprocess.run(child, check=True)


def _run_case(name, pts, run, check, repeats):
    """One case's row of the table, in this process."""
    mesh = knnrefine.refine(pts, **run)
    knnrefine.certify(mesh, pts, **check)  # warm: kernels compiled and loaded
    refine_t, certify_t, refine_mb, certify_mb = [], [], [], []
    for _ in range(repeats):
        mesh = None
        _trim()
        base = _status_mb("VmRSS")
        reset_peak()
        t0 = time.perf_counter()
        mesh = knnrefine.refine(pts, **run)
        refine_t.append(time.perf_counter() - t0)
        refine_mb.append(_status_mb("VmHWM") - base)
        _trim()
        base = _status_mb("VmRSS")
        reset_peak()
        t0 = time.perf_counter()
        cert = knnrefine.certify(mesh, pts, **check)
        certify_t.append(time.perf_counter() - t0)
        certify_mb.append(_status_mb("VmHWM") - base)
    r, c = statistics.median(refine_t), statistics.median(certify_t)
    rm, cm = statistics.median(refine_mb), statistics.median(certify_mb)
    print(f"| {name} | {len(pts):,} | {len(mesh.vertices):,} | {r:.2f} s | {c:.2f} s | "
          f"{c / r:.1f} | {rm:.0f}, {cm:.0f} MiB | {cert.n_probes:,} | {cert.passed} |",
          flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
