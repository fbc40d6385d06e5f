"""knnrefine on a read-only install (issue 8, item 5): the import works everywhere, and
kernels compiled into the package's own __pycache__ before it was made read-only are used.

The package is copied into a temporary folder and made read-only for real: bind-mounted
read-only in a user namespace (``unshare``; root ignores permission bits), or by permission
bits when the tests do not run as root. The home folder lies inside it, so numba has no
writable cache directory either."""

import json
import os
import shlex
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import knnrefine

PROBE = textwrap.dedent("""
    import json, warnings
    warnings.simplefilter("always")
    with warnings.catch_warnings(record=True) as caught:
        import numpy as np
        import knnrefine
        from knnrefine._engine import refine as R
        mesh = knnrefine.refine(np.random.default_rng(0).random((300, 2)), 5)
    print(json.dumps({
        "m": len(mesh.vertices),
        "file": knnrefine.__file__,
        "misses": sum(R.refine_steps.stats.cache_misses.values()),
        "hits": sum(R.refine_steps.stats.cache_hits.values()),
        "warnings": [w.category.__name__ for w in caught],
    }))
""")


def _environment(site):
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(PYTHONPATH=str(site), HOME=str(site / "home"))
    return env


def _run(command, env):
    out = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _read_only_runner():
    """A function running the probe with ``site`` read-only, or None if this machine cannot."""
    if os.geteuid() != 0:

        def run(site):
            for root, dirs, files in os.walk(site):
                for name in dirs + files:
                    os.chmod(os.path.join(root, name), 0o555)
            try:
                return _run([sys.executable, "-c", PROBE], _environment(site))
            finally:
                for root, dirs, files in os.walk(site):
                    for name in dirs + files:
                        os.chmod(os.path.join(root, name), 0o755)

        return run
    unshare = shutil.which("unshare")
    if unshare is None:
        return None
    probe = subprocess.run([unshare, "-rm", "true"], capture_output=True)
    if probe.returncode != 0:
        return None

    def run(site):
        probe = site / "probe.py"
        probe.write_text(PROBE)
        where = shlex.quote(str(site))
        script = (
            f"mount --bind {where} {where} && mount -o remount,bind,ro {where} && "
            f"exec {shlex.quote(sys.executable)} {shlex.quote(str(probe))}"
        )
        return _run([unshare, "-rm", "sh", "-c", script], _environment(site))

    return run


@pytest.fixture
def read_only():
    runner = _read_only_runner()
    if runner is None:
        pytest.skip("this machine cannot make a folder read-only for the test (no unshare)")
    return runner


def _copy_package(tmp_path):
    site = tmp_path / "site"
    shutil.copytree(
        Path(knnrefine.__file__).parent,
        site / "knnrefine",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    (site / "home").mkdir()
    return site


@pytest.mark.slow
def test_read_only_install_without_a_cache_imports_and_says_so(tmp_path, read_only):
    """Used to raise at import: "cannot cache function 'snap': no locator available"."""
    site = _copy_package(tmp_path)
    result = read_only(site)
    assert result["file"].startswith(str(site))
    assert result["m"] > 0
    assert "KernelCacheWarning" in result["warnings"]


@pytest.mark.slow
def test_read_only_install_uses_the_kernels_shipped_with_it(tmp_path, read_only):
    """Used to recompile from scratch (55 s), ignoring the shipped __pycache__."""
    site = _copy_package(tmp_path)
    warm = _run([sys.executable, "-c", PROBE], _environment(site))  # compiles into the copy
    assert warm["misses"] == 1
    assert list((site / "knnrefine" / "_engine" / "__pycache__").glob("*.nbi"))
    result = read_only(site)
    assert result["m"] == warm["m"]
    assert result["misses"] == 0 and result["hits"] == 1
    assert "KernelCacheWarning" not in result["warnings"]
