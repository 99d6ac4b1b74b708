"""The main job (`exolan pipeline`): every step runs in order, a failing step is reported (and makes the
exit status non-zero) without stopping the later ones, and the summary names every output.
The end-to-end run with the real parts is `test_pipeline_end_to_end` (slow)."""
from __future__ import annotations

import json

import pytest

from exolan import pipeline as P
from exolan import reproduce as R


def _stub(monkeypatch, fail=None):
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
    def fake_py(code, argv, log, timeout, label):
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
    failed = [s for s in summary["steps"] if s["status"] == "failed"]
    assert len(failed) == 1 and "evaluate" in failed[0]["error"]
    assert "**error**" in (tmp_path / "pipeline.md").read_text()


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


def test_a_timed_out_diagnosis_is_flagged_but_does_not_fail_the_job(monkeypatch, tmp_path):
    _stub(monkeypatch)

    def slow(*a, **k):
        raise P.StepTimeout("diagnose (quick settings) did not finish within 1 s")

    monkeypatch.setattr(P, "_run_py", slow)
    assert P.pipeline(tmp_path, log=lambda *a: None) == 0
    steps = json.loads((tmp_path / "pipeline.json").read_text())["steps"]
    assert steps[-1]["status"] == "timed out"
    assert "timed out" in (tmp_path / "pipeline.md").read_text()
