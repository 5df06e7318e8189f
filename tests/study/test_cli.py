"""The CLI contract: --help everywhere, one JSON object with --json, exit 2 + one line on bad input."""

import json
import os
import subprocess
import sys

import pytest

from study.cli import main


def run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_help_for_every_command(capsys):
    from study.cli import COMMANDS

    for name in COMMANDS:
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        out, _ = capsys.readouterr()
        assert "usage: hydrabench" in out and len(out) > 200


def test_scenes_json_is_one_object_and_plot_is_written(tmp_path, capsys):
    png = tmp_path / "sub" / "junction.png"
    code, out, err = run(["scenes", "--context", "junction", "--frames", "3", "--seed", "1", "--json",
                          "--plot", str(png)], capsys)
    assert code == 0
    result = json.loads(out)  # exactly one JSON document
    assert out.count("\n") == 1
    assert result["context"] == "junction" and result["frames"] == 3
    assert sum(result["actors_per_class"].values()) > 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(png.parent.glob("*.tmp*"))


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["scenes", "--context", "volcano"], "unknown context"),
        (["scenes", "--context", "fog", "--severity", "7"], "--severity: must be <= 5"),
        (["scenes", "--frames", "-2"], "must be >= 1"),
        (["scenes", "--frames", "0"], "must be >= 1"),
        (["scenes", "--context", "city", "--severity", "3"], "no weather condition"),
        (["scenes", "--seed", "abc"], "expected an integer"),
        (["nonsense"], "invalid choice"),
        (["scenes", "--plot", "/proc/forbidden/x.png"], "not writable"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, needle, capsys):
    code, out, err = run(argv, capsys)
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hydrabench"), err
    assert needle in lines[0]
    assert "Traceback" not in err


def test_installed_console_script_reports_errors_without_traceback(tmp_path):
    exe = os.path.join(os.path.dirname(sys.executable), "hydrabench")
    if not os.path.exists(exe):
        exe_cmd = [sys.executable, "-m", "study.cli"]
    else:
        exe_cmd = [exe]
    p = subprocess.run(exe_cmd + ["scenes", "--context", "fog", "--severity", "9"], capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    if os.access(ro, os.W_OK):  # running as root: permissions are not enforced
        return
    p = subprocess.run(exe_cmd + ["scenes", "--frames", "1", "--plot", str(ro / "x.png")], capture_output=True, text=True)
    assert p.returncode == 2 and "not writable" in p.stderr and not list(ro.iterdir())
