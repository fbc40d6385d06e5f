"""The first call's wait: a fresh process refining 2,000 points, in the plane, in space and on
the sphere, timed from before ``import knnrefine`` to the returned mesh, once with an empty
numba cache (the first-ever call: every kernel the call needs is compiled) and once more with
that cache (what every later process pays). Each domain runs in its own processes and cache,
so a figure is that domain's alone; the "compiling" notice each call shows is recorded too.
Each first call is made with the compile-ahead helper (``engine/ahead.py``: a second process
compiling the largest kernels) and without it (``KNNREFINE_COMPILE_AHEAD=0``), alternating,
each in a fresh cache; ``--ahead on`` or ``off`` makes only one of them.

    python benchmarks/first_call.py [--repeat 2] [--ahead both]
        [--out benchmarks/results/first_call.json]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

CALLS = {
    "plane": "knnrefine.refine(rng.random((2000, 2)), 10)",
    "space": "knnrefine.refine(rng.random((2000, 3)), 10)",
    "sphere": "knnrefine.refine(rng.random((2000, 2)) * [360, 180] - [180, 90], 10, sphere=True)",
}

CODE = """
import time
t = time.perf_counter()
import numpy as np
import knnrefine
rng = np.random.default_rng(0)
phases = []
def progress(v, p, phase="refining"):
    phases.append(phase)
knnrefine.refine  # imported
mesh = {call}
print("SECONDS", time.perf_counter() - t, "COMPILING", "compiling" in phases)
"""


def one(domain, cache, ahead=True):
    call = CALLS[domain].replace(", 10", ", 10, progress=progress", 1)
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, KNNREFINE_COMPILE_AHEAD="1" if ahead else "0")
    out = subprocess.run([sys.executable, "-c", CODE.format(call=call)], env=env, check=True,
                         capture_output=True, text=True).stdout.split()  # fmt: skip
    return float(out[out.index("SECONDS") + 1]), out[out.index("COMPILING") + 1] == "True"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=2, help="fresh caches per domain")
    ap.add_argument("--domains", nargs="+", default=list(CALLS))
    ap.add_argument(
        "--ahead",
        choices=["both", "on", "off"],
        default="both",
        help="first calls with the compile-ahead helper, without, or both",
    )
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    modes = {"both": [True, False], "on": [True], "off": [False]}[args.ahead]
    rows = []
    for domain in args.domains:
        first = {m: [] for m in modes}
        cached, said = [], []
        for _ in range(args.repeat):
            for m in modes:  # alternating: the machine's drift falls on both
                with tempfile.TemporaryDirectory() as cache:
                    s, c = one(domain, cache, m)
                    first[m].append(s)
                    said.append(c)
                    cached.append(one(domain, cache, m)[0])
        row = {"domain": domain, "cached_s": float(np.median(cached)), "cached_all_s": cached,
               "said_compiling": all(said)}  # fmt: skip
        for m in modes:
            key = "first" if m else "first_alone"
            row[f"{key}_s"] = float(np.median(first[m]))
            row[f"{key}_all_s"] = first[m]
        rows.append(row)
        parts = [f"{'with the helper' if m else 'one process'} "
                 f"{np.median(first[m]):.1f} s ({', '.join(f'{x:.1f}' for x in first[m])})"
                 for m in modes]  # fmt: skip
        print(f"{domain:>6}: first call (empty cache) {'; '.join(parts)}; later processes "
              f"{row['cached_s']:.2f} s; 'compiling' announced: {row['said_compiling']}",
              flush=True)  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
