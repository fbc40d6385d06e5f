"""The release path (issue 54): a wheel built once, installed into a fresh virtual environment
at another path, and the first calls a new user makes there, each in a new process, timed
whole (interpreter start and ``import knnrefine`` included):

* import knnrefine and refine 3,000 points, in the plane, in space and on the sphere (each
  domain in its own process; ``--busy`` repeats them with the other cores kept busy);
* the estimator's first fit + grid at 10^4 points after one at 3,000, against its second
  (while the process the first fit started compiles the kernel sums for this CPU, at the
  lowest priority; then how long after the first fit that compile was done);
* ``knnrefine demo``;
* ``import knnrefine`` alone.

Also the wheel's build time and size, and, with ``--source``, ``pip install . && knnrefine
demo`` into another fresh environment from this checkout (the build compiles the listed
kernels; ``KNNREFINE_BUILD_KERNELS=0`` builds without them, as before this issue, for the
comparison: ``--source both``).

The environments reuse this interpreter's installed dependencies (``--system-site-packages``,
the package installed with ``--no-deps``); the builds are pip's own (isolated: setuptools,
numba, numpy and scipy from the package index, which must offer the numba and numpy
installed here for the kernels to be used).

    python benchmarks/shipped_install.py [--repeat 3] [--busy] [--source both] [--keep DIR]

(``--keep``: the wheel is copied there, for ``benchmarks/portable_code.py``.)
"""

import argparse
import json
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

FIRST = """
import time
t = time.perf_counter()
import numpy as np
import knnrefine
rng = np.random.default_rng(0)
{call}
print("SECONDS", time.perf_counter() - t)
"""
CALLS = {
    "plane": "knnrefine.refine(rng.random((3000, 2)), 10)",
    "space": "knnrefine.refine(rng.random((3000, 3)), 10)",
    "sphere": "knnrefine.refine(rng.random((3000, 2)) * [360, 180] - [180, 90], 10, sphere=True)",
    "import": "pass",
}
WHERE = """
import json, knnrefine
from knnrefine._engine import shipped
print(json.dumps([knnrefine.__file__, shipped.build_marker()]))
"""
ESTIMATOR = """
import time
import numpy as np
import knnrefine
rng = np.random.default_rng(0)
from knnrefine._engine import shipped
knnrefine.KnnDensityEstimator().fit(rng.random((3000, 3)))  # starts the background compile
knnrefine.KnnDensityEstimator().fit(rng.random((3000, 2)))
started = time.perf_counter()
out = []
for seed in (1, 2):
    pts = np.random.default_rng(seed).random((10000, 2))
    t = time.perf_counter()
    knnrefine.KnnDensityEstimator().fit(pts).grid()
    out.append(time.perf_counter() - t)
state = shipped.upgrade("kernel sums in space", wait=True)  # this CPU's code, compiled meanwhile
print("SECONDS", *out, time.perf_counter() - started, state)
"""


def clean_env(venv):
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("NUMBA_", "PYTHON", "KNNREFINE_"))}  # fmt: skip
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["HOME"] = str(venv / "home")
    return env


def make_venv(where):
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(where)], check=True)
    (where / "home").mkdir()
    return where / "bin" / "python"


def timed(args, env, cwd=None):
    t = time.perf_counter()
    out = subprocess.run(args, env=env, cwd=cwd, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"{' '.join(map(str, args))} failed:\n{out.stderr[-3000:]}")
    return time.perf_counter() - t, out.stdout


def build_wheel(into, kernels=True):
    env = dict(os.environ, KNNREFINE_BUILD_KERNELS="1" if kernels else "0")
    args = [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-w", str(into), "-q"]
    shutil.rmtree(ROOT / "build", ignore_errors=True)
    seconds, _ = timed(args, env)
    wheel = next(Path(into).glob("knnrefine-*.whl"))
    return seconds, wheel


def hog(stop):
    while not stop.is_set():
        sum(i * i for i in range(10000))


def busy_cores():
    stop = multiprocessing.Event()
    procs = [multiprocessing.Process(target=hog, args=(stop,))
             for _ in range(max(1, (os.cpu_count() or 2) - 1))]  # fmt: skip
    for p in procs:
        p.start()
    return stop, procs


def first_calls(python, env, repeat, label):
    rows = {}
    for name, call in CALLS.items():
        times = []
        for _ in range(repeat):
            _, out = timed([python, "-c", FIRST.format(call=call)], env)
            times.append(float(out.split("SECONDS")[1].split()[0]))
        rows[name] = times
        print(f"  {label} {name:8s} " + " ".join(f"{t:.2f}" for t in times) + " s", flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--busy", action="store_true", help="also with the other cores busy")
    ap.add_argument("--source", choices=["none", "kernels", "both"], default="none")
    ap.add_argument("--keep", type=Path, help="copy the wheel into this folder")
    args = ap.parse_args(argv)
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        seconds, wheel = build_wheel(tmp / "dist")
        size = wheel.stat().st_size
        print(f"wheel built in {seconds:.1f} s, {size / 2**20:.1f} MiB ({wheel.name})")
        result["wheel"] = {"seconds": seconds, "MiB": size / 2**20}
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
            shutil.copy(wheel, args.keep)
        python = make_venv(tmp / "venv")
        env = clean_env(tmp / "venv")
        timed([python, "-m", "pip", "install", "-q", "--no-deps", str(wheel)], env)
        where, marker = json.loads(timed([python, "-c", WHERE], env)[1])
        if not where.startswith(str(tmp / "venv")):
            raise SystemExit(f"the fresh environment imports knnrefine from {where}")
        print(f"built with: {marker}")
        result["first calls"] = first_calls(python, env, args.repeat, "idle")
        if args.busy:
            stop, procs = busy_cores()
            try:
                result["first calls, busy"] = first_calls(python, env, args.repeat, "busy")
            finally:
                stop.set()
                for p in procs:
                    p.join()
        _, out = timed([python, "-c", ESTIMATOR], env)
        first, second, upgraded, state = out.split("SECONDS")[1].split()
        first, second = float(first), float(second)
        print(f"estimator at 10^4 after 3,000: first {first:.2f} s, second {second:.2f} s "
              f"({first / second:.2f}x); the kernel sums for this CPU: {state} "
              f"{float(upgraded):.0f} s after the first fit")  # fmt: skip
        result["estimator"] = [first, second]
        result["kernel sums upgraded"] = [state, float(upgraded)]
        demo = []
        for _ in range(args.repeat):
            seconds, _ = timed([tmp / "venv" / "bin" / "knnrefine", "demo", "-q", "--out",
                                str(tmp / "demo")], env)  # fmt: skip
            demo.append(seconds)
        print("knnrefine demo " + " ".join(f"{t:.1f}" for t in demo) + " s")
        result["demo"] = demo
        kinds = {"none": [], "kernels": [True], "both": [False, True]}[args.source]
        for kernels in kinds:
            venv = tmp / f"source-{kernels}"
            python = make_venv(venv)
            env = clean_env(venv)
            env["KNNREFINE_BUILD_KERNELS"] = "1" if kernels else "0"
            shutil.rmtree(ROOT / "build", ignore_errors=True)
            install, _ = timed([python, "-m", "pip", "install", "-q", "--no-deps", str(ROOT)],
                               env)  # fmt: skip
            env.pop("KNNREFINE_BUILD_KERNELS")
            demo, _ = timed([venv / "bin" / "knnrefine", "demo", "-q", "--out",
                             str(venv / "demo")], env)  # fmt: skip
            label = "with its kernels" if kernels else "without kernels (as before)"
            print(f"pip install . && knnrefine demo, {label}: {install:.1f} + {demo:.1f} = "
                  f"{install + demo:.1f} s")  # fmt: skip
            result[f"source, kernels {kernels}"] = [install, demo]
    shutil.rmtree(ROOT / "build", ignore_errors=True)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
