"""The ``emreg`` command: usage errors, exit codes, one-line messages."""

import os
import subprocess
import sys

import pytest

from EMRegModule.cli.main import build_parser, main


def test_version_and_help_through_the_console_script():
    result = subprocess.run([sys.executable, "-m", "EMRegModule", "--version"], capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.startswith("emreg ")
    help_text = subprocess.run([sys.executable, "-m", "EMRegModule", "--help"], capture_output=True, text=True).stdout
    for command in ("simulate", "detect", "calibrate", "register", "navigate", "evaluate", "report", "run", "demo"):
        assert command in help_text


def test_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as info:
        main(["frobnicate"])
    assert info.value.code == 2
    with pytest.raises(SystemExit) as info:
        main(["calibrate"])
    assert info.value.code == 2
    assert "error" in capsys.readouterr().err


def test_bad_input_is_one_line_exit_2(tmp_path, capsys):
    (tmp_path / "bad.csv").write_text("time_s,sensor\n1,2\n")
    code = main(["calibrate", str(tmp_path / "bad.csv"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "bad.csv" in err
    assert not (tmp_path / "out" / "frame_calibration.json").exists()


def test_run_without_ct_is_exit_2(tmp_path, capsys):
    code = main(["run", str(tmp_path), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 2 and "no CT" in capsys.readouterr().err


def test_missing_case_folder_is_exit_2(tmp_path, capsys):
    code = main(["run", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")])
    assert code == 2 and "case folder not found" in capsys.readouterr().err


def test_parser_knows_every_spec_option():
    parser = build_parser()
    args = parser.parse_args(["calibrate", "rec.csv", "--out", "o", "--reference-sensor", "3", "--probe-sensor", "4"])
    assert (args.reference_sensor, args.probe_sensor) == (3, 4)
    args = parser.parse_args(["register", "--markers", "m.json", "--calibration", "c.json", "--out", "o"])
    assert args.markers == "m.json"
    args = parser.parse_args(["navigate", "--registration", "r.json", "--source", "replay:n.csv", "--out", "o"])
    assert args.source == "replay:n.csv" and args.igtl_port is None
    args = parser.parse_args(["simulate", "o", "--seed", "3", "--difficulty", "hard", "--spacing", "0.8"])
    assert (args.seed, args.difficulty, args.spacing) == (3, "hard", 0.8)
    args = parser.parse_args(["evaluate", "case", "--registration", "r.json", "--out", "o"])
    assert args.case == "case"


@pytest.mark.parametrize("source", ["raise KeyboardInterrupt", 'exec("raise KeyboardInterrupt")'])
def test_ctrl_c_inside_a_string_exec_still_exits_130_under_python_m(tmp_path, source):
    """Ctrl-C landing while a library runs a string ``exec`` (dataclasses and namedtuples are made that way,
    so any lazy import can be the place) made ``python -m EMRegModule.cli.main`` die by SIGINT (-2) after printing
    its one line, although ``main`` returned 130: CPython then remembers the interrupt as unhandled."""
    (tmp_path / "interrupted_cli.py").write_text(
        "import sys\nfrom EMRegModule.cli import stages\nfrom EMRegModule.cli.main import main\n"
        f"def interrupted(args):\n    exec({source!r})\n"
        "stages.cmd_detect = interrupted\n"
        "sys.exit(main(['detect', 'CT', '--out', 'OUT']))\n")
    result = subprocess.run([sys.executable, "-m", "interrupted_cli"], cwd=tmp_path, capture_output=True,
                            text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert result.returncode == 130, result.stderr
    assert result.stderr.splitlines() == ["emreg detect: interrupted (SIGINT); no partial file was left in place "
                                          "of a complete one"]
