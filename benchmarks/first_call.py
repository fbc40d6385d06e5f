"""The first call's wait: a fresh process refining 2,000 points, in the plane, in space and on
the sphere, timed from before ``import knnrefine`` to the returned mesh, once with an empty
numba cache (the first-ever call: every kernel the call needs is compiled) and once more with
that cache (what every later process pays). Each domain runs in its own processes and cache,
so a figure is that domain's alone; the "compiling" notice each call shows is recorded too.

    python benchmarks/first_call.py [--repeat 2] [--out benchmarks/results/first_call.json]
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


def one(domain, cache):
    call = CALLS[domain].replace(", 10", ", 10, progress=progress", 1)
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    out = subprocess.run([sys.executable, "-c", CODE.format(call=call)], env=env, check=True,
                         capture_output=True, text=True).stdout.split()  # fmt: skip
    return float(out[out.index("SECONDS") + 1]), out[out.index("COMPILING") + 1] == "True"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=2, help="fresh caches per domain")
    ap.add_argument("--domains", nargs="+", default=list(CALLS))
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    rows = []
    for domain in args.domains:
        first, cached, said = [], [], []
        for _ in range(args.repeat):
            with tempfile.TemporaryDirectory() as cache:
                s, c = one(domain, cache)
                first.append(s)
                said.append(c)
                cached.append(one(domain, cache)[0])
        row = {"domain": domain, "first_s": float(np.median(first)), "first_all_s": first,
               "cached_s": float(np.median(cached)), "cached_all_s": cached,
               "said_compiling": all(said)}  # fmt: skip
        rows.append(row)
        print(f"{domain:>6}: first call {row['first_s']:.1f} s (empty cache; "
              f"{', '.join(f'{x:.1f}' for x in first)}), later processes {row['cached_s']:.2f} s,"
              f" 'compiling' announced: {row['said_compiling']}", flush=True)  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
