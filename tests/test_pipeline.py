"""The main job (`exolan pipeline`): every step runs in order, a failing or timed-out step is reported (the job's
status "partial", the step named in the summary's first line, a non-zero exit status) without stopping the later
ones, and the summary names every output.
The end-to-end run with the real parts is `test_pipeline_end_to_end` (slow)."""
from __future__ import annotations

import json

import pytest

from exolan import pipeline as P
from exolan import reproduce as R

_REAL_RUN_PY = P._run_py  # before any test replaces it


def _stub(monkeypatch, fail=None, failed_runs=()):
    calls = []

    def fake_world(out, scale, backend):
        (out / "world").mkdir(parents=True, exist_ok=True)
        return out / "world"

    def fake_reproduce(scale, out, data=None, log=print, **kw):
        sc = R.SCALES[scale]
        spec = R.RunSpec("world", "exolan", True, sc.w_fd, sc.w_ms, sc.seeds[0], sc.epochs, sc.batch_size)
        run = out / "runs" / spec.run_id / "train"
        run.mkdir(parents=True)
        (run / "checkpoint.pt").write_bytes(b"x")
        (out / "report.md").write_text("# report\n")
        calls.append("reproduce")
        return {"meta": {"failed_runs": list(failed_runs)}}

    def fake_cli(*args, log, timeout=None):
        calls.append(args[0])
        if args[0] == fail:
            raise RuntimeError(f"exolan {args[0]} exited with 1")
        i = args.index("--out")
        out = args[i + 1]
        if args[0] == "export":
            open(out, "wb").write(b"weights")
        elif args[0] == "diagnose":
            import os
            os.makedirs(out, exist_ok=True)
            json.dump({"findings": []}, open(os.path.join(out, "diagnosis.json"), "w"))
        else:
            open(out, "w").write("{}")

    monkeypatch.setattr(R, "ensure_world", fake_world)
    monkeypatch.setattr(R, "reproduce", fake_reproduce)
    monkeypatch.setattr(P, "_cli", fake_cli)
    def fake_py(code, argv, log, timeout, label, keep=None):
        import os
        calls.append("diagnose")
        os.makedirs(argv[2], exist_ok=True)
        json.dump({"findings": []}, open(os.path.join(argv[2], "diagnosis.json"), "w"))

    monkeypatch.setattr(P, "_run_py", fake_py)
    monkeypatch.setattr(P, "_parity", lambda *a: {"parity_max_abs_q": 0.0})
    return calls


def test_pipeline_runs_every_step_in_order(monkeypatch, tmp_path):
    calls = _stub(monkeypatch)
    assert P.pipeline(tmp_path, log=lambda *a: None) == 0
    assert calls == ["reproduce", "evaluate", "export", "rollout", "diagnose"]
    summary = json.loads((tmp_path / "pipeline.json").read_text())
    assert summary["ok"] and [s["status"] for s in summary["steps"]] == ["ok"] * 6
    md = (tmp_path / "pipeline.md").read_text()
    assert "reproduce/report.md" in md and "exolan.safetensors" in md


def test_a_failing_step_is_reported_and_later_steps_still_run(monkeypatch, tmp_path):
    calls = _stub(monkeypatch, fail="evaluate")
    assert P.pipeline(tmp_path, log=lambda *a: None) == 1
    assert calls[-1] == "diagnose"
    summary = json.loads((tmp_path / "pipeline.json").read_text())
    assert summary["status"] == "partial" and not summary["ok"]
    failed = [s for s in summary["steps"] if s["status"] == "failed"]
    assert len(failed) == 1 and "evaluate" in failed[0]["error"]
    md = (tmp_path / "pipeline.md").read_text()
    assert md.splitlines()[0] == "# exolan main job: partial (step 'evaluate the pipeline model' failed)"
    assert "**error**" in md
    assert (tmp_path / "exolan.safetensors").exists() and (tmp_path / "rollouts.json").exists()


def test_no_trained_model_fails_the_job_and_skips_what_needs_it(monkeypatch, tmp_path):
    calls = _stub(monkeypatch)

    def broken(*a, **k):
        raise RuntimeError("out of memory")

    monkeypatch.setattr(R, "reproduce", broken)
    assert P.pipeline(tmp_path, log=lambda *a: None) == 1
    assert calls == []
    summary = json.loads((tmp_path / "pipeline.json").read_text())
    assert summary["status"] == "failed"
    assert [s["status"] for s in summary["steps"]] == ["ok", "failed"] + ["skipped"] * 4
    assert (tmp_path / "pipeline.md").read_text().startswith("# exolan main job: failed (step 'train")


def test_failed_runs_of_the_sweep_make_the_job_partial(monkeypatch, tmp_path):
    _stub(monkeypatch, failed_runs=["world/mlp_fd0_ms0_e3_b1024_s1"])
    assert P.pipeline(tmp_path, log=lambda *a: None) == 1
    summary = json.loads((tmp_path / "pipeline.json").read_text())
    study = summary["steps"][1]
    assert study["status"] == "partial" and study["failed_runs"] == ["world/mlp_fd0_ms0_e3_b1024_s1"]
    assert summary["status"] == "partial"
    assert [s["status"] for s in summary["steps"][2:]] == ["ok"] * 4  # the model was trained: the rest ran


@pytest.mark.slow
def test_pipeline_end_to_end(tmp_path):
    """simulate -> train -> evaluate -> export -> Rust rollouts -> diagnose -> report, with the real parts,
    at the test-only micro scale."""
    assert P.pipeline(tmp_path, scale="micro") == 0
    summary = json.loads((tmp_path / "pipeline.json").read_text())
    rust = next(s for s in summary["steps"] if s["step"] == "Rust rollouts")
    assert rust["parity_max_abs_q"] < 1e-8
    for f in ("reproduce/report.md", "evaluation.json", "exolan.safetensors", "rollouts.json",
              "diagnosis/diagnosis.md", "pipeline.md"):
        assert (tmp_path / f).stat().st_size > 0, f


def test_a_timed_out_diagnosis_makes_the_job_partial_and_exolan_pipeline_exit_non_zero(monkeypatch, tmp_path,
                                                                                        small_world):
    """The diagnosis step runs for real (its own process, on a tiny world) under a bound of 10 ms, which no
    Python process can meet: it is stopped, reported as timed out, and `exolan pipeline` exits non-zero
    while every other step's outputs stay."""
    import shutil

    from exolan import cli

    _stub(monkeypatch)
    monkeypatch.setattr(P, "_run_py", _REAL_RUN_PY)
    monkeypatch.setattr(R, "ensure_world", lambda out, scale, backend: shutil.copytree(small_world, out / "world"))
    monkeypatch.setenv("EXOLAN_DIAGNOSE_TIMEOUT", "0.01")
    out = tmp_path / "job"
    assert cli.main(["pipeline", "--out", str(out)]) == 1
    summary = json.loads((out / "pipeline.json").read_text())
    assert summary["status"] == "partial"
    assert [s["status"] for s in summary["steps"]] == ["ok"] * 5 + ["timed out"]
    assert "0.01 s" in summary["steps"][-1]["error"]
    assert (out / "pipeline.md").read_text().splitlines()[0] == \
        "# exolan main job: partial (step 'diagnose' timed out)"
    for f in ("evaluation.json", "exolan.safetensors", "rollouts.json", "reproduce/report.md", "world/subjects.csv"):
        assert (out / f).exists(), f
    assert not (out / "diagnosis" / "diagnosis.json").exists()


def test_a_step_in_its_own_process_shows_its_lines_as_they_come_and_keeps_them(tmp_path):
    """The diagnosis step prints a line at least every 30 s: the job passes each on while the step still runs
    (not its tail at the end) and keeps them all in a file."""
    import time

    got = []
    code = "import time; print('first', flush=True); time.sleep(3); print('second', flush=True)"
    _REAL_RUN_PY(code, [], log=lambda line: got.append((time.monotonic(), line)), timeout=60, label="probe",
                 keep=tmp_path / "probe.log")
    lines = {line.strip(): t for t, line in got}
    assert lines["second"] - lines["first"] > 1.5           # the first was passed on before the step ended
    assert (tmp_path / "probe.log").read_text().split() == ["first", "second"]

