"""Orchestration of the paper's studies (`exolan reproduce`): planning, the real-data split, resumable
sweeps, local process pool vs serial vs Ray giving the same numbers, and the report's content.

The tests use a stand-in backend (`standin.py`: a tiny synthetic world and closed-form "models" with the
documented model interface) so that the orchestration is exercised in seconds; the real models are exercised by
`test_reproduce_real.py`, the forward-dynamics metrics by `test_rollout_metrics.py`."""
from __future__ import annotations

import dataclasses
import json
import os
import secrets
import sys
from pathlib import Path

import numpy as np
import pytest

from exolan import reproduce as R
from standin import fake_world

HERE = Path(__file__).resolve().parent
STANDIN = "standin:StandInBackend"

def test_plan_has_16_methods_per_seed_and_shares_the_inverse_only_run():
    specs = R.plan(R.SCALES["small"], with_real=False)
    world = [s for s in specs if s.dataset == "world"]
    for seed in R.SCALES["small"].seeds:
        intent = {(s.arch, s.lim) for s in world if s.seed == seed and s.w_fd == 0 and s.w_ms == 0}
        assert len(intent) == 16
        fd = [s for s in world if s.seed == seed and s.arch == "exolan" and s.lim]
        assert len(fd) == 3  # inverse only (shared with the intention study), + w_fd, + w_fd & w_ms
    assert len({s.run_id for s in specs}) == len(specs)
    paper = R.SCALES["paper"]
    assert paper.epochs == 1000 and len(paper.seeds) == 5


def test_converge_plan_early_stops_every_world_run_and_trains_both_normalisations():
    sc = R.SCALES["converge"]
    specs = R.plan(sc, with_real=True)
    world = [s for s in specs if s.dataset == "world"]
    assert len(sc.seeds) >= 3 and sc.users == 21 and sc.tasks == "all"
    assert all(s.patience > 0 and s.val_users >= 1 for s in world)            # validation from training users
    assert not any(s.patience for s in specs if s.dataset == "real")          # one training user: fixed epochs
    for seed in sc.seeds:
        mine = [s for s in world if s.seed == seed]
        intent = {(s.arch, s.lim) for s in mine if s.w_fd == 0 and s.w_ms == 0}
        assert {("exolan", True), ("exolan", False), ("mlp-tcn", True), ("tcn", True), ("delan", True),
                ("mlp", True), ("delan-lstm", True)} <= intent
        ms = {s.ms_norm for s in mine if s.w_ms > 0}
        assert ms == {"increment", "state"}                                   # ours and the paper's
        assert any(s.w_fd > 0 and s.w_ms == 0 for s in mine)
        assert {s.ms_horizon for s in mine if s.w_ms > 0} == {4, 20}           # the paper's H and a longer one
    assert len({s.run_id for s in specs}) == len(specs)
    assert [s.run_id for s in specs if s.ms_horizon == 20][0].endswith("_increment_h20n51_p10v2_e150_b2048_s0")
    # every horizon's rollout loss costs a batch the same model evaluations: the paper's 256 starts x 4 steps
    assert {s.ms_starts * s.ms_horizon // 4 for s in world if s.w_ms > 0} <= {255, 256}
    # the ids of the earlier scales are unchanged (finished runs of an interrupted study are reused)
    small = R.RunSpec("world", "exolan", True, 0.01, 1.0, 0, 3, 1024)
    assert small.run_id == "world/exolan_fd0.01_ms1_e3_b1024_s0"


def test_the_real_backend_trains_a_spec_with_its_own_rollout_starts(monkeypatch, tmp_path):
    from exolan import reproduce_job, train as tr

    seen = {}
    monkeypatch.setattr(tr, "train", lambda trials, **kw: seen.update(kw))
    monkeypatch.setattr(tr, "load_run", lambda run_dir, device: (None, None))
    spec = [s for s in R.plan(R.SCALES["converge"], with_real=False) if s.ms_horizon == 20][0]
    reproduce_job.RealBackend().train(spec, [], tmp_path, "", "cpu", 1)
    assert (seen["horizon"], seen["n_starts"], seen["ms_norm"], seen["patience"]) == (20, 51, "increment", 10)


def test_real_split_is_disjoint_and_covers_the_three_held_out_kinds():
    trials = []
    for subj, task, name in [("REAL01", "walk", "walk_1_1"), ("REAL01", "walk", "walk_2_1"),
                             ("REAL01", "walk", "walk_3_1"), ("REAL01", "squat", "squat_1_1"),
                             ("REAL01", "squat_asym", "squat_asym_1_1"), ("REAL04", "walk", "walk_1_1")]:
        tr = fake_world(users=1, tasks=("walk",), T=100)[0]
        trials.append(dataclasses.replace(tr, subject=subj, task=task, name=name))
    train, tests = R.real_split(trials)
    assert [t.name for t in train] == ["walk_1_1", "walk_2_1", "squat_1_1"]
    assert len(train[-1].q) == 70 and len(tests["seen"][-1].q) == 30  # time split of a single trial
    assert [t.name for t in tests["seen"]] == ["walk_3_1", "squat_1_1"]
    assert [t.task for t in tests["unseen_task"]] == ["squat_asym"]
    assert [t.subject for t in tests["unseen_user"]] == ["REAL04"]


def _metrics(out: Path) -> dict:
    """Everything numeric the runs produced, minus wall-clock times."""
    res = {}
    for f in sorted((out / "runs").rglob("result.json")):
        r = json.loads(f.read_text())
        for k in ("train_seconds", "eval_seconds"):
            r.pop(k)
        res[str(f.relative_to(out))] = r
    return res


@pytest.fixture(scope="module")
def fake_real(tmp_path_factory):
    d = tmp_path_factory.mktemp("fake_real")
    (d / "real.json").write_text("{}")
    return str(d)


@pytest.fixture(scope="module")
def tiny_serial(tmp_path_factory, fake_real):
    out = tmp_path_factory.mktemp("tiny_serial")
    summary = R.reproduce("tiny", out, workers=1, backend=STANDIN, real_dir=fake_real, log=lambda *a: None)
    return out, summary


def test_tiny_sweep_writes_a_complete_report(tiny_serial):
    out, summary = tiny_serial
    md = (out / "report.md").read_text()
    for heading in ("## 1. Human intention estimation", "## 2. Forward dynamics",
                    "## 3. Task identification", "## 4. Real recordings"):
        assert heading in md
    assert "paper (real data)" in md
    res = json.loads((out / "results.json").read_text())
    assert len(res["intention"]) == 6  # tiny: 3 architectures x with/without LIM
    assert set(res["forward_dynamics"]) == {"inverse", "w_fd", "w_fd+w_ms", "w_fd+w_ms (H = 6)"}  # tiny: H 4 and 6
    assert any(c["claim"] == "multi-step loss lowers qd20 MSE (w_fd+w_ms (H = 6) vs w_fd)" for c in res["fd_claims"])
    assert "| **ours** ExoLaN (w_fd, w_ms, H = 6, 170 starts)" in md
    assert "### Where the multi-step loss acts: q̇_20 MSE per task and joint" in md
    per_task = res["forward_dynamics"]["w_fd"]["per_task"]
    assert {d["split"] for d in per_task.values()} == {"seen", "unseen"} and "squat" in per_task
    assert res["task_identification"]["sample_split"]["exolan"]["accuracy"][0] > 0
    assert any(c["claim"].startswith("ExoLaN+LIM vs TCN+LIM") for c in res["intention_claims"])
    assert set(res["real"]) == {"exolan", "mlp-tcn", "tcn"}
    assert float(res["real"]["exolan"]["unseen_user"]["mse"][0]) > 0
    assert "real_mse_bars" in res["figures"]
    for name in ("mse_bars", "torque_tasks", "accelerations", "rollouts", "rollout_error_growth",
                 "task_identification"):
        png = out / res["figures"][name]
        assert png.stat().st_size > 10_000, name  # a real drawing, not an empty canvas
        assert f"]({res['figures'][name]})" in md


def test_rerun_skips_finished_runs_and_gives_identical_numbers(tiny_serial, fake_real):
    out, _ = tiny_serial
    before = _metrics(out)
    first = json.loads((out / "sweep_clock.json").read_text())
    lines = []
    R.reproduce("tiny", out, workers=1, backend=STANDIN, real_dir=fake_real, log=lines.append, write_report=False)
    assert any("0 to run" in l for l in lines), lines
    assert _metrics(out) == before
    # the sweep's wall time adds up over invocations: a resumed sweep still reports what the whole cost
    clock = json.loads((out / "sweep_clock.json").read_text())
    assert len(clock["sessions"]) == len(first["sessions"]) + 1
    assert clock["sessions"][-1]["runs_run"] == 0 and first["sessions"][0]["runs_run"] > 0
    assert clock["total"] >= first["total"] > 0


def test_interrupted_sweep_resumes_only_missing_runs(tiny_serial, fake_real, tmp_path):
    out, _ = tiny_serial
    import shutil
    shutil.copytree(out, tmp_path / "s")
    victim = next((tmp_path / "s" / "runs").rglob("DONE"))
    victim.unlink()  # as if killed before this run finished
    lines = []
    R.reproduce("tiny", tmp_path / "s", workers=1, backend=STANDIN, real_dir=fake_real, log=lines.append, write_report=False)
    assert any("1 to run" in l for l in lines), lines
    a, b = _metrics(out), _metrics(tmp_path / "s")
    assert a == b
    last = json.loads((tmp_path / "s" / "sweep_clock.json").read_text())["sessions"][-1]
    assert last["runs_run"] == 1 and last["finished"] and set(last["seconds"]) == {"world", "runs", "reference"}


def test_a_killed_invocation_keeps_its_time_up_to_its_last_finished_run(tmp_path):
    from exolan.report.markdown import _wall_time
    killed = R.SweepClock(tmp_path, "here")
    killed.update({"world": 10.0, "runs": 100.0}, 3)           # then the process dies: no finishing update
    on_disk = json.loads((tmp_path / "sweep_clock.json").read_text())
    assert on_disk["total"] == 110.0 and not on_disk["sessions"][0]["finished"]
    clock = R.SweepClock(tmp_path, "here").update({"world": 0.0, "runs": 50.0, "reference": 5.0}, 2, finished=True)
    assert clock["total"] == 165.0 and [s["runs_run"] for s in clock["sessions"]] == [3, 2]
    line = _wall_time({"sweep_clock": clock, "seconds": {"world": 0.0, "runs": 50.0}})
    assert "2.8 min" in line and "2 invocations, 1 interrupted" in line


@pytest.fixture(scope="module")
def tiny_pool(tmp_path_factory, fake_real):
    out = tmp_path_factory.mktemp("tiny_pool")
    R.reproduce("tiny", out, workers=2, backend=STANDIN, real_dir=fake_real, log=lambda *a: None, write_report=False)
    return out


def test_process_pool_gives_the_serial_numbers(tiny_serial, tiny_pool):
    out, _ = tiny_serial
    assert _metrics(tiny_pool) == _metrics(out)


def test_report_shows_per_joint_where_a_claim_fails(tiny_serial):
    """Per-joint MSEs add up to the pooled MSE, and every claim that does not hold gets its per-joint and
    per-task breakdown in the report."""
    out, summary = tiny_serial
    m = summary["intention"]["exolan"]["unseen"]
    assert np.mean([j[0] for j in m["per_joint"]]) == pytest.approx(m["mse"][0], rel=1e-9)
    md = (out / "report.md").read_text()
    failing = [c for c in summary["intention_claims"] + summary["real_claims"] if c["verdict"] != "holds"]
    assert failing, "the stand-in's claims should not all hold"
    assert "### Where the claims that do not hold fail" in md
    for c in failing:
        assert f"| {c['claim']} |" in md.split("### Where the claims that do not hold fail", 1)[1]
    assert "Wall time of the sweep" in md


@pytest.mark.ray
@pytest.mark.heavy  # 16 s alone, 22 s (plus 40 s of fixtures) beside other tests at load 12 on two cores
def test_ray_path_gives_the_local_numbers(tiny_pool, fake_real, tmp_path, monkeypatch):
    """`--ray local`: a fresh local Ray instance runs the tiny sweep (22 runs) and is stopped after it; the numbers
    are those of the local process pool. Ray is a test dependency: where it is missing this fails, not skips."""
    import ray

    # the instance's workers inherit this environment: the stand-in backend's module on their path; no usage
    # report over the network; no cluster address from outside; room for slow worker start-up on a busy machine;
    # a new local instance enables token authentication (Ray 2.60): its token given here, so that Ray does not
    # write one to ~/.ray/auth_token
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE)] + sys.path))
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    monkeypatch.setenv("RAY_AUTH_TOKEN", secrets.token_hex(32))
    monkeypatch.delenv("RAY_AUTH_TOKEN_PATH", raising=False)
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setenv("RAY_worker_register_timeout_seconds", "300")
    lines = []
    try:
        R.reproduce("tiny", tmp_path, backend=STANDIN, real_dir=fake_real, ray_address="local", log=lines.append,
                    write_report=False)
        assert not ray.is_initialized()  # the sweep stopped the instance it started
    finally:
        if ray.is_initialized():
            ray.shutdown()
    n = len(R.plan(R.SCALES["tiny"], with_real=True))
    assert any(f"{n} to run (ray local" in line for line in lines), lines
    assert not any("FAILED" in line for line in lines), lines
    assert _metrics(tmp_path) == _metrics(tiny_pool)


def test_default_workers_is_one_per_core_within_free_memory(monkeypatch):
    avail = {"bytes": 5 * R.WORKER_BYTES}
    monkeypatch.setattr(R, "_available_memory", lambda: avail["bytes"])
    assert R.default_workers(16) == 5          # memory for five jobs
    assert R.default_workers(3) == 3           # fewer cores than that
    avail["bytes"] = 0
    assert R.default_workers(16) == 1          # always at least one
    avail["bytes"] = None
    assert R.default_workers(16) == 16         # unknown memory: one per core


def test_available_memory_reads_a_positive_figure():
    assert R._available_memory() > 0


def test_a_run_marker_survives_a_larger_plan_but_not_other_evaluation(tmp_path, monkeypatch):
    from exolan import reproduce_exec as X
    from exolan import study

    ctx = X.JobContext(out=str(tmp_path), data_dir=str(tmp_path / "world"), real_dir=None, scale="tiny", backend=None)
    spec = R.plan(R.SCALES["tiny"], with_real=False)[0]
    key = X._spec_key(spec, ctx)
    tiny = R.SCALES["tiny"]
    monkeypatch.setitem(study.SCALES, "tiny", dataclasses.replace(tiny, seeds=(0, 1, 2), ms_horizons=(4, 8)))
    assert X._spec_key(spec, ctx) == key                       # more runs in the plan: this one is still done
    assert X._spec_key(dataclasses.replace(spec, ms_horizon=4), ctx) == key   # a field at its default
    assert X._spec_key(dataclasses.replace(spec, seed=7), ctx) != key
    monkeypatch.setitem(study.SCALES, "tiny", dataclasses.replace(tiny, rollout_stride=tiny.rollout_stride + 1))
    assert X._spec_key(spec, ctx) != key                       # evaluated differently: not the same result


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_pool_workers_end_with_a_killed_sweep(tmp_path):
    """A sweep ended by SIGKILL/SIGTERM of its process alone (no Ctrl-C to the group) leaves no workers."""
    import subprocess
    import time

    script = tmp_path / "sweep.py"
    script.write_text(
        "import os, sys, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from exolan.reproduce_exec import _worker_init\n"
        "if __name__ == '__main__':\n"
        "    ex = ProcessPoolExecutor(1, initializer=_worker_init, initargs=(1,))\n"
        "    print(ex.submit(os.getpid).result(), flush=True)\n"
        "    ex.submit(time.sleep, 600)\n"
        "    time.sleep(600)\n")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1] / "python"))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env)
    worker = int(proc.stdout.readline())
    proc.kill()
    proc.wait()
    for _ in range(100):
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    os.kill(worker, 9)
    pytest.fail("the pool worker outlived its killed sweep")
