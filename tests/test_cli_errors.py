"""Every CLI error is one line on stderr, `exolan COMMAND: what (which file). Expected: ...`, with a non-zero
exit status and no traceback (EXOLAN_DEBUG=1 shows it). Each command that takes files is fed a bad file or a
missing folder; the commands run in this process (fast), and the issue's own example runs through the real
entry point."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from exolan import cli


def _bad_inputs(tmp: Path) -> dict:
    """name -> (argv, the bad path the line must name); every path under tmp."""
    (tmp / "afile").write_text("not a folder\n")
    (tmp / "data").mkdir()                                 # exists; never read before the bad input fails
    trial = tmp / "world" / "S01" / "walk_1_1"
    trial.mkdir(parents=True)
    for f in ("Exo.csv", "Joint_Moments_Filt.csv"):
        (trial / f).write_text("")   # truncated to nothing
    run = tmp / "run"
    run.mkdir()
    (run / "model.json").write_text('{"method": "exolan", ')     # cut short mid-file
    (tmp / "bad.toml").write_text("epochs = [\n")
    w = tmp / "model.safetensors"
    w.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{\"a\":")  # a header longer than the file
    missing = tmp / "missing"
    return {
        "simulate out under a file": (["simulate", "--out", str(tmp / "afile" / "w"), "--users", "1"], "afile"),
        "plot missing folder": (["plot", str(missing), "--out", str(tmp / "p.png")], "missing"),
        "plot empty csv": (["plot", str(trial), "--out", str(tmp / "p.png")], "walk_1_1"),
        "train missing data": (["train", "--data", str(missing), "--out", str(tmp / "r")], "missing"),
        "train bad config": (["train", "--data", str(tmp / "data"), "--config", str(tmp / "bad.toml"),
                              "--out", str(tmp / "r")], "bad.toml"),
        "train negative threads": (["train", "--data", str(tmp / "data"), "--threads", "-1", "--out", str(tmp / "r")],
                                   "threads"),
        "evaluate missing run": (["evaluate", str(missing), "--data", str(tmp / "data")], "missing"),
        "evaluate truncated run": (["evaluate", str(run), "--data", str(tmp / "data")], "run"),
        "export truncated run": (["export", str(run), "--out", str(tmp / "x.safetensors")], "run"),
        "rollout truncated weights": (["rollout", str(w), "--data", str(tmp / "data")], "model.safetensors"),
        "rollout missing data": (["rollout", str(w), "--data", str(missing)], "missing"),
        "reproduce missing data": (["reproduce", "--data", str(missing), "--out", str(tmp / "s")], "missing"),
        "reproduce out under a file": (["reproduce", "--out", str(tmp / "afile" / "s")], "afile"),
        "diagnose missing data": (["diagnose", str(missing), "--out", str(tmp / "d")], "missing"),
        "diagnose empty data": (["diagnose", str(tmp / "data"), "--out", str(tmp / "d")], "data"),
        "diagnose missing model": (["diagnose", str(tmp / "data"), "--model", str(missing), "--out", str(tmp / "d")],
                                   "missing"),
        "pipeline out under a file": (["pipeline", "--out", str(tmp / "afile" / "job")], "afile"),
    }


CASES = [  # the keys of _bad_inputs (checked in the test)
    "simulate out under a file", "plot missing folder", "plot empty csv", "train missing data", "train bad config",
    "train negative threads",
    "evaluate missing run", "evaluate truncated run", "export truncated run", "rollout truncated weights",
    "rollout missing data", "reproduce missing data", "reproduce out under a file", "diagnose missing data",
    "diagnose empty data", "diagnose missing model", "pipeline out under a file"]


def _one_line_error(err: str, command: str, names: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"exolan {command}: "), err
    assert "Traceback" not in err and names in lines[0], err
    return lines[0]


@pytest.mark.parametrize("case", CASES)
def test_a_bad_input_is_one_line_naming_the_file(case, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("EXOLAN_DEBUG", raising=False)
    cases = _bad_inputs(tmp_path)
    assert set(cases) == set(CASES)
    argv, names = cases[case]
    capsys.readouterr()
    rc = cli.main(argv)
    assert rc == 2, rc
    line = _one_line_error(capsys.readouterr().err, argv[0], names)
    assert "Expected: " in line, line  # what to do: what the input must be


def test_an_unexpected_error_is_one_line_and_exolan_debug_shows_the_traceback(tmp_path, capsys, monkeypatch):
    import exolan.export

    def broken(args):
        raise TypeError("unsupported operand type(s) for +: 'int' and 'str'\n  second line")

    monkeypatch.setattr(exolan.export, "cli_export", broken)
    (tmp_path / "run").mkdir()
    argv = ["export", str(tmp_path / "run"), "--out", str(tmp_path / "x.safetensors")]
    monkeypatch.delenv("EXOLAN_DEBUG", raising=False)
    assert cli.main(argv) == 1
    line = _one_line_error(capsys.readouterr().err, "export", "TypeError")
    assert "EXOLAN_DEBUG=1" in line and "second line" in line
    monkeypatch.setenv("EXOLAN_DEBUG", "1")
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("Traceback") and err.splitlines()[-1].startswith("exolan export: unexpected TypeError")


def test_a_missing_package_is_one_line_saying_how_to_install_it(tmp_path, capsys, monkeypatch):
    import exolan.reproduce

    def no_ray(args):
        raise ModuleNotFoundError("No module named 'ray'", name="ray")

    monkeypatch.setattr(exolan.reproduce, "cli_reproduce", no_ray)
    assert cli.main(["reproduce", "--out", str(tmp_path / "s"), "--ray", "local"]) == 2
    line = _one_line_error(capsys.readouterr().err, "reproduce", "'ray'")
    assert "pip install 'exolan[ray]'" in line


def test_a_usage_error_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["rollout", str(tmp_path)])  # --data missing
    assert exc.value.code == 2
    _one_line_error(capsys.readouterr().err, "rollout", "--data")


def test_the_truncated_weight_file_of_the_issue_through_the_entry_point(tmp_path):
    """`exolan rollout` on a truncated .safetensors printed a 14-line traceback: now one line, exit 2."""
    w = tmp_path / "exolan.safetensors"
    w.write_bytes(b"\x80\x00\x00\x00\x00\x00\x00\x00{\"w\": {\"dtype\": \"F64\"")
    env = {k: v for k, v in os.environ.items() if k != "EXOLAN_DEBUG"}
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "rollout", str(w), "--data", str(tmp_path)],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 2, r.stderr
    line = _one_line_error(r.stderr, "rollout", str(w))
    assert "not a valid safetensors weight file" in line and "`exolan export`" in line
