"""Where the first-ever compile goes: numba's stages, and the functions that cost most.

Runs the benchmark's compile workload (refine 2,000 points in a box, then on the torus; with
``--domain space`` the same in the unit cube) in a fresh process with an empty numba cache
and times, exclusive of nested compilations, numba's type inference, lowering (IR
generation, with the CPython wrappers), inlining, and LLVM's optimisation and machine-code
generation.

    python benchmarks/compile_profile.py [--top 15] [--domain space]
"""

import argparse
import collections
import os
import subprocess
import sys
import tempfile
import time

WORKLOAD = """
import numpy as np, knnrefine
p = np.random.default_rng(0).random((2000, 2))
knnrefine.refine(p, 10)
knnrefine.refine(p, 10, periodic=True, box=(0, 0, 1, 1))
"""
WORKLOAD3 = """
import numpy as np, knnrefine
p = np.random.default_rng(0).random((2000, 3))
knnrefine.refine(p, 10)
knnrefine.refine(p, 10, periodic=True, box=(0, 0, 0, 1, 1, 1))
"""


def profile(top, workload=WORKLOAD):
    """In this process (its numba cache must be empty): stage and per-function times."""
    from numba.core import codegen, typed_passes, untyped_passes

    stages = collections.Counter()
    functions = collections.Counter()
    stack = []

    def timed(cls, method, stage):
        original = getattr(cls, method)

        def wrapper(self, *args, **kwargs):
            state = args[0] if args else None
            name = getattr(getattr(state, "func_id", None), "func_qualname", None)
            stack.append(0.0)
            t0 = time.perf_counter()
            try:
                return original(self, *args, **kwargs)
            finally:
                spent = time.perf_counter() - t0
                own = spent - stack.pop()
                stages[stage] += own
                if name:
                    functions[f"{stage} {name}"] += own
                if stack:
                    stack[-1] += spent

        setattr(cls, method, wrapper)

    timed(typed_passes.BaseTypeInference, "run_pass", "typing")
    timed(typed_passes.NativeLowering, "run_pass", "lowering")
    timed(untyped_passes.InlineInlinables, "run_pass", "inlining")
    timed(codegen.CPUCodeLibrary, "_optimize_functions", "LLVM optimisation")
    timed(codegen.CPUCodeLibrary, "_optimize_final_module", "LLVM optimisation")
    timed(codegen.JITCodeLibrary, "_finalize_specific", "LLVM code generation")
    timed(codegen.CPUCodeLibrary, "add_ir_module", "LLVM IR parsing")
    t0 = time.perf_counter()
    exec(workload, {})
    total = time.perf_counter() - t0
    print(f"first compile (import included): {total:.2f} s")
    for stage, seconds in stages.most_common():
        print(f"  {seconds:6.2f} s  {stage}")
    print(f"  {total - sum(stages.values()):6.2f} s  everything else (import, caching, running)")
    print(f"costliest (stage, function), exclusive of nested compilations, top {top}:")
    for key, seconds in functions.most_common(top):
        print(f"  {seconds:6.2f} s  {key}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--domain", choices=["plane", "space"], default="plane")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        profile(args.top, WORKLOAD3 if args.domain == "space" else WORKLOAD)
        return
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        cmd = [sys.executable, __file__, "--child", "--top", str(args.top), "--domain",
               args.domain]  # fmt: skip
        subprocess.run(cmd, env=env, check=True)


if __name__ == "__main__":
    main()
