"""Every command and every Python example in README.md runs as written (issue 9).

The shell block is run line by line in a temporary folder (``cd`` changes it, as in a
shell), through the installed ``knnrefine`` console script; the two first commands' installs
are what the test run itself stands on, so of them only ``knnrefine demo`` is run. The Python
blocks run in order in one namespace, as a reader would paste them."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def blocks(language):
    """The fenced code blocks of README.md whose info string is ``language`` ("" for none),
    in order."""
    found, current, info = [], None, None
    for line in README.read_text().splitlines(keepends=True):
        if line.startswith("```"):
            if current is None:
                current, info = [], line[3:].strip()
            else:
                if info == language:
                    found.append("".join(current))
                current = None
        elif current is not None:
            current.append(line)
    return found


def shell_commands():
    """The README's command lines: its first block's demo, then the command-line block."""
    commands = []
    first = blocks("")[0]
    assert first.splitlines()[0].startswith("pip install . && knnrefine demo")
    commands.append("knnrefine demo")
    for block in blocks(""):
        if block.lstrip().startswith("knnrefine demo "):
            text = block.replace("\\\n", " ")
            for line in text.splitlines():
                line = line.split("  #")[0].strip()  # comments are two spaces and a hash
                if line and line != commands[0] and not line.startswith("knnrefine demo"):
                    commands.append(line)
    return commands


def test_the_readme_has_what_this_test_runs():
    commands = shell_commands()
    assert commands[0] == "knnrefine demo" and commands[1] == "cd knnrefine-demo"
    names = {c.split()[1] for c in commands if c.startswith("knnrefine ")}
    assert {"refine", "certify", "plot", "density", "persistence", "cluster"} <= names


def test_the_readmes_geographic_examples_use_the_sphere():
    """A new user's (issue 50): the README's first command-line example refined the
    earthquakes' longitude and latitude as a planar box periodic in x. Geographic data
    (quakes.csv) goes through --sphere (or a mesh made with it), and the periodic box is
    for planar data (the torsion angles)."""
    for command in shell_commands():
        if "quakes.csv" in command and command.split()[1] in ("refine", "density", "cluster"):
            assert "--sphere" in command or "--mesh world.npz" in command, command
        if "--periodic" in command:
            assert "angles.csv" in command, command


@pytest.mark.slow
def test_every_readme_command_runs_as_written(tmp_path):
    if shutil.which("knnrefine") is None:
        pytest.skip("the knnrefine console script is not installed (pip install .)")
    pytest.importorskip("gudhi")
    cwd = tmp_path
    for command in shell_commands():
        if command.startswith("cd "):
            cwd = cwd / command[3:].strip()
            assert cwd.is_dir(), command
            continue
        out = subprocess.run(command, shell=True, cwd=cwd, capture_output=True, text=True)
        assert out.returncode == 0, f"{command}\n{out.stdout}\n{out.stderr}"
    for made in (
        "angles.npz",
        "angles.vtu",
        "angles.png",
        "cells.svg",
        "density.png",
        "diagram.png",
        "labels.csv",
        "clusters.png",
        "certificate-angles.json",
        "certificate-world.json",
        "world.npz",
        "world.geojson",
        "world.png",
        "world-density.npz",
        "world-density.png",
    ):
        assert (cwd / made).stat().st_size > 0, made


@pytest.mark.slow
def test_every_readme_python_example_runs(tmp_path, monkeypatch):
    pytest.importorskip("gudhi")
    monkeypatch.chdir(tmp_path)  # the examples write torus.npz
    namespace = {}
    for code in blocks("python"):
        exec(compile(code, str(README), "exec"), namespace)  # noqa: S102
    assert namespace["cert"].passed
    assert namespace["again"].k == namespace["torus"].k
    assert os.path.exists(tmp_path / "torus.npz")
    assert namespace["world"].on_sphere and os.path.exists(tmp_path / "world.geojson")


@pytest.mark.slow
def test_the_readme_sphere_block_runs_as_a_script_and_from_stdin(tmp_path):
    """The sphere's block, pasted into a script or piped to python, runs cleanly and writes
    its GeoJSON and map."""
    import subprocess
    import sys

    block = next(b for b in blocks("python") if "sphere=True" in b)
    code = "import knnrefine\n" + block
    script = tmp_path / "sphere.py"
    script.write_text(code)
    for args, stdin in (([str(script)], None), (["-"], code)):
        run = subprocess.run([sys.executable, *args], input=stdin, capture_output=True,
                             text=True, timeout=600, cwd=tmp_path)  # fmt: skip
        assert run.returncode == 0, run.stderr[-3000:]
        assert "Traceback" not in run.stderr and "Warning" not in run.stderr, run.stderr
        assert (tmp_path / "world.geojson").stat().st_size > 0
        assert (tmp_path / "world.png").stat().st_size > 50_000


@pytest.mark.slow
def test_the_readme_workers_and_dask_block_runs_as_a_script_and_from_stdin(tmp_path):
    """regression (issue 28): the README's workers/Dask block, pasted into a script, flooded
    stderr with 'Failed to start process' (Dask spawned its workers, which imports the
    script again, without a main guard), and from stdin raised 'Nanny failed to start'.
    The block as written, on 30,000 points, runs cleanly both ways."""
    import subprocess
    import sys

    pytest.importorskip("distributed")
    block = next(b for b in blocks("python") if "distributed.refine" in b)
    code = (
        "import numpy as np\nimport knnrefine\n"
        "points = np.random.default_rng(0).random((30_000, 2))\n" + block
    )
    script = tmp_path / "example.py"
    script.write_text(code)
    for args, stdin in (([str(script)], None), (["-"], code)):
        run = subprocess.run([sys.executable, *args], input=stdin, capture_output=True,
                             text=True, timeout=600, cwd=tmp_path)  # fmt: skip
        assert run.returncode == 0, run.stderr[-3000:]
        assert "Failed to start" not in run.stderr and "Traceback" not in run.stderr
        assert (tmp_path / "parts" / "_SUCCESS").exists()
