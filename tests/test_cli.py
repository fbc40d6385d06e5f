import shutil
import subprocess
import sys

import pytest

from knnrefine.cli.main import main


def test_demo_in_process(capsys):
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert "n = 18748" in out and "d_M2 / d_Pk in [" in out


def test_demo_as_console_script():
    exe = shutil.which("knnrefine")
    cmd = (
        [exe, "demo", "-k", "50"]
        if exe
        else [sys.executable, "-m", "knnrefine.cli.main", "demo", "-k", "50"]
    )
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    assert "k = 50" in out


def test_usage_errors_exit_2():
    with pytest.raises(SystemExit) as info:
        main(["no-such-command"])
    assert info.value.code == 2


def test_bad_parameter_exits_1(capsys):
    assert main(["demo", "--tau", "1.5"]) == 1
    assert "tau must be > 2" in capsys.readouterr().err
