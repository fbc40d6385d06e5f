"""Where certify's memory goes, stage by stage, in one of ``certify_speed``'s cases.

    python benchmarks/certify_memory.py plane-uniform-k10
    python benchmarks/certify_memory.py space-clustered-box-k10 --trim

Each of certify's steps (the domain's ``Geometry`` and ``Points`` methods, ``bounded_d_pk``,
the points' tree build) is timed, while a thread samples the process's resident memory
every half millisecond; for each step the table gives its start and end (seconds into the
call) and the resident memory above the call's start at its start, its peak within and at
its end. ``--trim`` returns freed heap memory to the system after each step (glibc's
malloc_trim): what is left then is what is held, not what the allocator kept. One warm-up
refine and certify first (kernels compiled and loaded); Linux only (/proc).
"""

import argparse
import functools
import os
import sys
import threading
import time
import warnings

import numpy as np

import knnrefine
from knnrefine._domains import part
from knnrefine.certify import _tree, steps

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_refine import _status_mb, _trim, reset_peak  # noqa: E402
from certify_speed import cases  # noqa: E402

PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20
STEPS = ("triangulation", "returned_problems", "cells", "held", "precondition", "probes",
         "returned_d_m2", "size")  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case", help="one of certify_speed's cases")
    ap.add_argument("--trim", action="store_true", help="trim the heap after each step")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    pts, run, check = cases(1.0)[args.case]
    mesh = knnrefine.refine(pts, **run)
    knnrefine.certify(mesh, pts, **check)  # warm
    domain = part(mesh.domain, "certify")
    log = []

    def timed(owner, name, label):
        fn = getattr(owner, name)

        @functools.wraps(fn)
        def wrapper(*a, **kw):
            t0 = time.perf_counter()
            out = fn(*a, **kw)
            if args.trim:
                _trim()
            log.append((label, t0, time.perf_counter()))
            return out

        setattr(owner, name, wrapper)

    for name in STEPS:
        timed(domain.Geometry, name, name)
    for name in ("cell_counts", "d_pk", "fewer"):
        timed(domain.Points, name, "points." + name)
    timed(steps, "bounded_d_pk", "bounded_d_pk")
    timed(_tree, "_build", "the points' tree")
    _trim()
    base = _status_mb("VmRSS")
    reset_peak()
    samples, stop = [], []

    def sampler():
        with open("/proc/self/statm") as f:
            while not stop:
                f.seek(0)
                samples.append((time.perf_counter(), int(f.read().split()[1]) * PAGE_MB))
                time.sleep(0.0005)

    thread = threading.Thread(target=sampler, daemon=True)
    thread.start()
    t0 = time.perf_counter()
    cert = knnrefine.certify(mesh, pts, **check)
    seconds = time.perf_counter() - t0
    stop.append(True)
    thread.join()
    trimmed = " (the heap trimmed after each step)" if args.trim else ""
    print(f"{args.case}: certify {seconds:.2f} s, peak {_status_mb('VmHWM') - base:.0f} MiB "
          f"above its start{trimmed}, passed {cert.passed}\n")  # fmt: skip
    print("| step | from, to (s) | at its start | peak | at its end |")
    print("|---|---|---:|---:|---:|")
    at = np.array(samples)
    # a step called inside another (the cells a walk reads) is the other's; a step asked
    # several times in a row (in chunks) is one row (the tree is built in a thread of its
    # own, beside the steps)
    log.sort(key=lambda e: e[1])
    outer = [e for e in log if e[0] == "the points' tree" or not any(
        o is not e and o[0] != "the points' tree" and o[1] <= e[1] and e[2] <= o[2]
        for o in log)]  # fmt: skip
    merged = []
    for label, a, b in outer:
        if merged and merged[-1][0] == label:
            merged[-1][2], merged[-1][3] = b, merged[-1][3] + 1
        else:
            merged.append([label, a, b, 1])
    for label, a, b, calls in merged:
        label = label if calls == 1 else f"{label} ({calls} calls)"
        inside = (at[:, 0] >= a) & (at[:, 0] <= b)
        before = at[at[:, 0] <= a]
        if not inside.any() or not len(before):
            continue
        start, peak, end = before[-1, 1], at[inside, 1].max(), at[inside][-1, 1]
        print(f"| {label} | {a - t0:.3f}, {b - t0:.3f} | {start - base:.0f} MiB | "
              f"{peak - base:.0f} MiB | {end - base:.0f} MiB |")  # fmt: skip


if __name__ == "__main__":
    main()
