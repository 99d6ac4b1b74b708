"""Orchestration of the paper's studies (`exolan reproduce`): planning, the real-data split, resumable
sweeps, local process pool vs serial vs Ray giving the same numbers, and the report's content.

Most tests use a stand-in backend (defined here: a tiny synthetic world and closed-form "models" with
the documented model interface) so that the orchestration is exercised in seconds; the real models are
exercised by `test_reproduce_real.py`."""
from __future__ import annotations

import dataclasses
import json
import os
import secrets
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from exolan import reproduce as R
from exolan.data import Trial

HERE = Path(__file__).resolve().parent
STANDIN = "test_reproduce:StandInBackend"


# ------------------------------------------------------------------------------------------------------
# Stand-in backend: same contracts as exolan.data / exolan.models, no learning beyond least squares
# ------------------------------------------------------------------------------------------------------

# the stand-in backend builds real Trial records (the data contract), filled by least-squares stand-ins
FakeTrial = Trial


TRAIN_TASKS = ("walk", "stand", "calisthenics", "push_pull", "jump_in_place", "turn", "cut")


def fake_world(users=6, tasks=TRAIN_TASKS + ("run", "squat", "ball_toss"), T=160, seed=0):
    rng = np.random.default_rng(seed)
    trials = []
    for u in range(users):
        mass = 60 + 5 * u
        for k, task in enumerate(tasks):
            for side in ("l", "r"):
                t = np.arange(T) * 0.005
                w = 2 * np.pi * (0.8 + 0.15 * k)
                ph = rng.uniform(0, 2 * np.pi, 2)
                amp = np.array([0.5, 0.8]) * (0.5 + 0.05 * k)
                q = amp * np.sin(w * t[:, None] + ph)
                qd = amp * w * np.cos(w * t[:, None] + ph)
                qdd = -amp * w ** 2 * np.sin(w * t[:, None] + ph)
                fv = np.maximum(0, np.sin(w * t + ph[0])) * mass * 9.81
                tau = mass * (0.02 * qdd + 0.5 * np.sin(q) + 0.01 * qd) + 0.03 * fv[:, None]
                tau = tau + rng.normal(0, 0.5, tau.shape)
                valid = np.ones(T, bool)
                valid[:3] = False
                trials.append(FakeTrial(f"S{u:02d}", task, f"{task}_1_1", side, float(mass), 0.005,
                                        ("hip", "knee"), ("revolute", "revolute"), q, qd, qdd, tau,
                                        np.zeros_like(tau), fv, np.zeros((T, 2)), valid))
    return trials


class FakeModel(torch.nn.Module):
    """tau = a*qdd + W [sin q, cos q, qd, f_v, z, 1]: linear, so forward dynamics is (tau - rest)/a."""

    def __init__(self, dz, seed):
        super().__init__()
        g = torch.Generator().manual_seed(1234)
        self.dz = dz
        self.Wz = torch.nn.Parameter(torch.randn(7, dz, generator=g, dtype=torch.float64) * 0.1,
                                     requires_grad=False)
        self.a = torch.nn.Parameter(torch.ones(2, dtype=torch.float64), requires_grad=False)
        self.W = torch.nn.Parameter(torch.zeros(7 + dz, 2, dtype=torch.float64), requires_grad=False)

    def context(self, x):
        x = torch.nan_to_num(x)
        return torch.tanh(x @ self.Wz / 50.0)

    def _feat(self, q, qd, z, fv):
        return torch.cat([torch.sin(q), torch.cos(q), qd, fv[..., None] / 100, z], -1)

    def inverse(self, q, qd, qdd, z, f_v):
        return self.a * qdd + self._feat(q, qd, z, f_v) @ self.W

    def forward_dynamics(self, q, qd, tau, z, f_v):
        return (tau - self._feat(q, qd, z, f_v) @ self.W) / self.a


class StandInBackend:
    def simulate(self, out, scale):
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "fake.json").write_text(json.dumps({"users": scale.users, "seed": scale.world_seed}))

    def load(self, data_dir):
        if (Path(data_dir) / "real.json").exists():  # stand-in for shared/real: REAL01 + two other people
            trials = []
            for tr in fake_world(users=3, T=200, seed=5):
                subj = {"S00": "REAL01", "S01": "REAL02", "S02": "REAL03"}[tr.subject]
                task = tr.task if subj == "REAL01" or tr.task == "walk" else None
                if task is None:
                    continue
                if subj == "REAL01" and task in ("squat", "ball_toss"):
                    task = task + "_asym"  # unseen variants of the one person with many trials
                trials.append(dataclasses.replace(tr, subject=subj, task=task, name=f"{task}_1_1"))
            return trials
        p = Path(data_dir) / "fake.json"
        cfg = json.loads(p.read_text()) if p.exists() else {"users": 6, "seed": 0}
        return fake_world(users=cfg["users"], seed=cfg["seed"])

    def split(self, trials):
        subs = sorted({t.subject for t in trials})
        held = set(subs[len(subs) - len(subs) // 3:])
        train = [t for t in trials if t.subject not in held and t.task in TRAIN_TASKS]
        seen = [t for t in trials if t.subject in held and t.task in TRAIN_TASKS]
        unseen = [t for t in trials if t.subject in held and t.task not in TRAIN_TASKS]
        return train, seen, unseen

    def context_features(self, tr):
        return np.concatenate([tr.q, tr.qd, tr.f_v[:, None], tr.cop], 1)

    def task_groups(self):
        return {"walk": "cyclic", "run": "cyclic"}

    def train(self, spec, train, run_dir, data_dir, device, threads):
        dz = 0 if spec.arch in ("mlp", "delan") else 3
        m = FakeModel(dz, spec.seed)
        ckpt = Path(run_dir) / "model.pt"
        if ckpt.exists():  # resume = reuse
            m.load_state_dict(torch.load(ckpt))
            return m
        X, Y = [], []
        with torch.no_grad():
            for tr in train:
                z = m.context(torch.as_tensor(self.context_features(tr))[None])[0]
                f = m._feat(torch.as_tensor(tr.q), torch.as_tensor(tr.qd), z, torch.as_tensor(tr.f_v))
                X.append(torch.cat([f, torch.as_tensor(tr.qdd)], 1).numpy()[tr.valid])
                Y.append(tr.tau[tr.valid])
        X, Y = np.concatenate(X), np.concatenate(Y)
        rng = np.random.default_rng(spec.seed)
        lam = 1e-3 * (1 + rng.random()) * (10 if not spec.lim else 1)
        coef = np.linalg.solve(X.T @ X + lam * len(X) * np.eye(X.shape[1]), X.T @ Y)
        with torch.no_grad():
            m.W.copy_(torch.as_tensor(coef[:-2]))
            m.a.copy_(torch.as_tensor(np.clip(np.diag(coef[-2:]), 1e-3, None)))
        torch.save(m.state_dict(), ckpt)
        return m


# ------------------------------------------------------------------------------------------------------
# tests
# ------------------------------------------------------------------------------------------------------

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


def test_forward_dynamics_metrics_on_a_model_that_is_exact():
    """A model whose inverse dynamics produced the torques recovers q̈ exactly; its open-loop rollouts
    then only carry the integrator's error, which grows with the horizon, and match a plain loop."""
    scale = R.SCALES["tiny"]
    tr = fake_world(users=1, tasks=("walk",), T=200)[0]
    m = FakeModel(3, 0)
    with torch.no_grad():
        m.W.copy_(torch.randn(m.W.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.1)
        m.a.copy_(torch.tensor([0.5, 0.3], dtype=torch.float64))
        z = m.context(torch.as_tensor(StandInBackend().context_features(tr))[None])[0]
        tau = m.inverse(*(torch.as_tensor(a) for a in (tr.q, tr.qd, tr.qdd)), z, torch.as_tensor(tr.f_v))
    tr = dataclasses.replace(tr, tau=tau.numpy())
    rows = R._fd_metrics(m, [("seen", tr, z)], torch.float64, scale)
    assert sum(rows[0]["sse_qdd"]) / rows[0]["n_qdd"] < 1e-20
    h = rows[0]["horizons"]
    mse = [sum(h[str(k)]["sse_q"]) / h[str(k)]["n"] for k in scale.horizons]
    assert 0 < mse[0] < mse[1] < mse[2] < 1e-3
    # the first start, integrated by hand
    s = int(np.flatnonzero(np.convolve(tr.valid.astype(int), np.ones(21, int), "valid") == 21)[0])
    q, qd = torch.as_tensor(tr.q[s]), torch.as_tensor(tr.qd[s])
    for k in range(4):
        qdd = m.forward_dynamics(q, qd, tau[s + k], z[s + k], torch.as_tensor(tr.f_v[s + k]))
        qd = qd + tr.dt * qdd
        q = q + tr.dt * qd
    assert h["4"]["n"] >= 1
    assert float(((q.numpy() - tr.q[s + 4]) ** 2).sum()) <= h["4"]["sse_q"][0] + h["4"]["sse_q"][1] + 1e-15


def test_rollout_amplification_separates_integrated_from_compounding_errors():
    """A persistent q̈ error is integrated as it is (A ≈ 1 at every horizon), one that flips sign every step
    mostly cancels (A ≪ 1), and one that feeds back through the rolled-out velocity compounds (A grows with
    the horizon): the number the report uses to say why a multi-step loss can or cannot help."""
    from exolan import report

    scale = R.SCALES["tiny"]
    tr = fake_world(users=1, tasks=("walk",), T=200)[0]
    T, dt, n = len(tr.q), tr.dt, tr.q.shape[1]
    qdd = np.tile([[0.7, -0.4]], (T, 1))               # constant acceleration: semi-implicit Euler is exact
    qd = np.cumsum(np.vstack([np.zeros((1, n)), dt * qdd[:-1]]), axis=0) + 0.2
    q = np.cumsum(np.vstack([np.zeros((1, n)), dt * qd[1:]]), axis=0)
    tr = dataclasses.replace(tr, q=q, qd=qd, qdd=qdd, valid=np.ones(T, bool))
    bias = np.array([3.0, -2.0])

    def amp(error):
        def forward(q_, qd_, tau, z, fv, cx, owner, t):
            return qdd[t] + error(qd_ - qd[t], t)
        rows = R.rollout_metrics(forward, [("seen", tr, None)], scale)
        st = report.fd_stats([{"fd_rows": rows, "torque_rows": []}], scale.horizons, rows[0]["dt"])
        return [st["mean_std"][f"amp{h}"][0] for h in scale.horizons]

    persistent = amp(lambda dqd, t: bias)
    assert np.allclose(persistent, 1.0, atol=1e-9)
    flipping = amp(lambda dqd, t: bias * np.where(t % 2 == 0, 1.0, -1.0)[:, None])
    assert max(flipping) < 0.1
    compounding = amp(lambda dqd, t: bias + 60.0 * dqd)
    assert 1.0 < compounding[0] < compounding[1] < compounding[2]
    assert compounding[2] > 3.0


def test_forward_dynamics_errors_are_located_per_task_and_joint():
    """A q̈ error planted on one task's knee shows on that task and joint only, and the report's table puts the
    multi-step loss' change where it happened: how a reader sees where the multi-step claim fails."""
    from exolan import report
    from exolan.report.markdown import _fd_where_table

    scale = R.SCALES["tiny"]
    def integrated(tr):                                # q, q̇ exactly what semi-implicit Euler makes of q̈
        qd = tr.qd[0] + np.vstack([np.zeros((1, 2)), np.cumsum(tr.dt * tr.qdd[:-1], axis=0)])
        q = tr.q[0] + np.vstack([np.zeros((1, 2)), np.cumsum(tr.dt * qd[1:], axis=0)])
        return dataclasses.replace(tr, q=q, qd=qd, valid=np.ones(len(tr.q), bool))

    walk, squat = (integrated(tr) for tr in fake_world(users=1, tasks=("walk", "squat"), T=200)[::2])
    items = [("seen", walk, None), ("unseen", squat, None)]

    def stats(knee_error):
        def forward(q, qd, tau, z, fv, cx, owner, t):
            out = np.where(owner[:, None] == 0, walk.qdd[t], squat.qdd[t])
            return out + np.where(owner == 1, knee_error, 0.0)[:, None] * np.array([0.0, 1.0])
        rows = R.rollout_metrics(forward, items, scale)
        return report.fd_stats([{"fd_rows": rows, "torque_rows": []}], scale.horizons, rows[0]["dt"])

    a, b = stats(2.0), stats(1.0)
    h = scale.horizons[-1]
    assert a["per_task"]["walk"]["split"] == "seen" and a["per_task"]["squat"]["split"] == "unseen"
    assert a["per_task"]["walk"][f"qd{h}"] < 1e-20
    hip, knee = a["per_task"]["squat"][f"qd{h}_joints"]
    assert hip < 1e-20 < knee
    assert a["per_task"]["squat"]["qdd"] == pytest.approx(2.0, rel=1e-9)          # (0 + 2²) / 2 joints
    assert a["per_joint"]["qdd"][0] < 1e-20 < a["per_joint"]["qdd"][1]
    assert np.mean(a["per_joint"][f"qd{h}"]) == pytest.approx(a["mean_std"][f"qd{h}"][0], rel=1e-9)
    table = "\n".join(_fd_where_table({"w_fd": a, "w_fd+w_ms": b}, h))
    squat_row = next(line for line in table.splitlines() if line.startswith("| squat |"))
    change = squat_row.split(" | ")[5]
    assert change.startswith("-75.0% (") and change.endswith(" / -75.0%)")   # half the error: a quarter of the MSE
    assert squat_row.endswith("| — | — |")                                   # no floor given


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
