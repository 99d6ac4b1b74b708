"""Training on a small simulated world: it learns, the loss terms reach the gradient, chunks reproduce the
whole-trial context, config keys are strict, and a killed run resumes to the uninterrupted result."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from exolan.config import TrainConfig, load_config, merge
from exolan.data import context_features, load, paper_split
from exolan.evaluate import evaluate
from exolan.models import build_model
from exolan.train import batch_losses, compute_stats, load_run, make_chunks, train


@pytest.fixture(scope="module")
def split(small_world):
    return paper_split(load(small_world))


@pytest.fixture(scope="module")
def tiny(split):
    """Two users x two tasks: enough to exercise every code path quickly."""
    users = sorted({t.subject for t in split.train})[:2]
    return split.train.select(subjects=users, tasks={"walk", "jump_in_place"})


def test_exolan_and_mlp_tcn_learn_held_out_torque(split, tmp_path):
    """A few epochs bring held-out torque MSE well below the torque variance (seen tasks, unseen users)."""
    r2 = {}
    for method, epochs in (("exolan", 8), ("mlp-tcn", 8)):
        rd = train(split, method, epochs=epochs, seed=0, out=tmp_path / method, progress=False,
                   batch_size=1024, val_every=0, threads=1)
        model, meta = load_run(rd)
        res = evaluate(model, list(split.test_seen))["torque"]
        assert res["n"] > 5000
        assert res["mse"] < 0.3 * res["var"], (method, res["mse"], res["var"])
        r2[method] = res["r2"]
        # the per-epoch log holds every epoch, the held-out figure at the last one
        assert [m["epoch"] for m in meta["metrics"]] == list(range(1, epochs + 1))
        assert meta["metrics"][-1]["test_tau_mse"] == pytest.approx(res["mse"], rel=1e-6)
    assert r2["exolan"] >= 0.8, r2


def test_chunks_cover_each_sample_once_and_reproduce_trial_context(tiny):
    trials = list(tiny)[:3]
    model = build_model("exolan", context_channels=[f"c{i}" for i in range(7)]).double()
    with torch.no_grad():
        for p in model.encoder.parameters():
            p.copy_(torch.randn_like(p) * 0.3)
    stats = compute_stats(trials)
    model.norm.set_stats(stats["ctx_mean"], stats["ctx_std"])
    ch = make_chunks(trials, warmup=62, steps=100, horizon=4, dtype=torch.float64)
    assert int(ch.loss.sum()) == sum(int(t.valid.sum()) for t in trials)
    with torch.no_grad():
        z_chunks = model.context(ch.ctx, ch.keep)[:, 62:]            # (K, 100, 16)
        row = 0
        for t in trials:
            z = model.context(torch.as_tensor(context_features(t), dtype=torch.float64).unsqueeze(0))[0]
            K = -(-len(t.q) // 100)
            got = z_chunks[row:row + K].reshape(-1, 16)[: len(t.q)]
            assert z.abs().max() > 0.1
            torch.testing.assert_close(got, z, rtol=0, atol=1e-12)
            np.testing.assert_array_equal(ch.q[row:row + K, 62:].reshape(-1, 2)[: len(t.q)].numpy()[t.valid],
                                          t.q[t.valid])
            row += K
    assert row == ch.q.shape[0]


def test_every_loss_term_reaches_the_gradient(tiny):
    trials = list(tiny)[:2]
    stats = compute_stats(trials)
    torch.manual_seed(0)
    model = build_model("exolan", lim=True, context_channels=[f"c{i}" for i in range(7)], v_scale=20.0)
    model.norm.set_stats(stats["ctx_mean"], stats["ctx_std"])
    cfg = TrainConfig(w_fd=0.01, w_ms=1.0, horizon=4, n_starts=32, chunk_steps=64)
    ch = make_chunks(trials, 62, 64, 4)
    iv = torch.ones(2)
    terms = batch_losses(model, ch, torch.arange(4), cfg, iv, iv, trials[0].dt, torch.Generator().manual_seed(0))
    assert set(terms) == {"tau", "fd", "ms", "loss"}
    for name in ("tau", "fd", "ms"):
        grads = torch.autograd.grad(terms[name], list(model.parameters()), retain_graph=True, allow_unused=True)
        total = sum(float(g.abs().sum()) for g in grads if g is not None)
        assert total > 0, name
        # the encoder and the LIM learn from every term
        enc = torch.autograd.grad(terms[name], list(model.encoder.parameters()) + list(model.lim.parameters()),
                                  retain_graph=True)
        assert sum(float(g.abs().sum()) for g in enc) > 0, name
    total = terms["tau"] + 0.01 * terms["fd"] + 1.0 * terms["ms"]
    assert float(terms["loss"].detach()) == pytest.approx(float(total.detach()), rel=1e-6)


def test_config_keys_are_strict(tmp_path, tiny):
    p = tmp_path / "c.toml"
    p.write_text('method = "mlp"\nepochs = 2\nlearning_rate = 0.1\n')
    with pytest.raises(ValueError, match="learning_rate"):
        merge(load_config(p))
    p.write_text('method = "exolan"\n[model]\nhiden = 3\n')
    with pytest.raises(ValueError, match="hiden"):
        merge(load_config(p))
    p.write_text('method = "delan"\nepochs = 3\nw_fd = 0.5\n[model]\nhidden = 8\n')
    cfg = merge(load_config(p), epochs=1, w_fd=None)
    assert (cfg.method, cfg.epochs, cfg.w_fd, cfg.model) == ("delan", 1, 0.5, {"hidden": 8})
    with pytest.raises(ValueError, match="momentum"):
        train(tiny, "delan", epochs=1, out=tmp_path / "r", momentum=0.9)
    with pytest.raises(ValueError, match="black box"):
        train(tiny, "mlp", epochs=1, out=tmp_path / "r2", w_fd=0.1, progress=False)


_CHILD = r"""
import sys
from exolan.data import load, paper_split
from exolan.train import train
sp = paper_split(load(sys.argv[1]))
users = sorted({t.subject for t in sp.train})[:2]
tiny = sp.train.select(subjects=users, tasks={"walk", "jump_in_place"})
train(tiny, "exolan", epochs=int(sys.argv[3]), seed=3, out=sys.argv[2], progress=False, resume=True,
      batch_size=512, chunk_steps=128, w_fd=0.01, w_ms=1.0, n_starts=64, threads=1)
"""


def test_killed_and_resumed_run_ends_where_uninterrupted_run_ends(small_world, tiny, tmp_path):
    epochs = 5
    kw = dict(seed=3, progress=False, batch_size=512, chunk_steps=128, w_fd=0.01, w_ms=1.0, n_starts=64, threads=1)
    ref = train(tiny, "exolan", epochs=epochs, out=tmp_path / "ref", **kw)

    run = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", _CHILD, str(small_world), str(run), str(epochs)])
    metrics = run / "metrics.jsonl"
    deadline = time.time() + 300
    while time.time() < deadline and child.poll() is None:
        if metrics.exists() and len(metrics.read_text().splitlines()) >= 2:
            break
        time.sleep(0.02)
    assert child.poll() is None, "the child finished before it could be killed"
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    done = len(metrics.read_text().splitlines())
    assert 2 <= done < epochs
    assert json.loads((run / "run.json").read_text())["status"] == "running"

    with pytest.raises(FileExistsError):
        train(tiny, "exolan", epochs=epochs, out=run, **kw)               # no silent overwrite
    train(tiny, "exolan", epochs=epochs, out=run, resume=True, **kw)
    m_ref, meta_ref = load_run(ref)
    m_res, meta_res = load_run(run)
    for k, v in m_ref.state_dict().items():
        torch.testing.assert_close(m_res.state_dict()[k], v, rtol=0, atol=1e-6)
    assert [m["epoch"] for m in meta_res["metrics"]] == list(range(1, epochs + 1))
    for a, b in zip(meta_ref["metrics"], meta_res["metrics"]):
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-6, abs=1e-9)
    assert len((run / "metrics.jsonl").read_text().splitlines()) == epochs
    assert not list(run.glob("*.tmp*"))

    # a different seed gives a different model (the seed is not ignored)
    other = train(tiny, "exolan", epochs=1, out=tmp_path / "other", **{**kw, "seed": 4})
    m_other, _ = load_run(other)
    assert not torch.equal(m_other.state_dict()["delan.L.0.weight"], m_ref.state_dict()["delan.L.0.weight"])


def test_cli_train_and_evaluate(small_world, tmp_path):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text('batch_size = 2048\nthreads = 2\n[model]\nhidden = 16\n')
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "train", "--data", str(small_world), "--method", "delan",
                        "--no-lim", "--epochs", "2", "--seed", "1", "--config", str(cfg), "--device", "cpu",
                        "--threads", "1", "--out", str(run)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert json.loads((run / "run.json").read_text())["torch_threads"] == 1     # the flag wins over the file
    assert (run / "checkpoint.pt").exists() and (run / "norm.json").exists()
    phys = json.loads((run / "physics.json").read_text())
    assert phys["positive_definite"] is True and "cond(H)" in r.stdout
    spec = json.loads((run / "model.json").read_text())
    assert spec["method"] == "delan" and spec["lim"] is False and spec["hidden"] == 16
    assert spec["v_scale"] > 0
    conf = json.loads((run / "config.json").read_text())
    assert conf["batch_size"] == 2048 and conf["epochs"] == 2
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "evaluate", str(run), "--data", str(small_world)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    res = json.loads((run / "evaluation.json").read_text())
    for part in ("seen", "unseen"):
        assert res[part]["torque"]["mse"] > 0
        assert set(res[part]["torque"]["per_joint"]) == {"hip", "knee"}
        assert set(res[part]["forward"]["q"]) == {"4", "10", "20"}
    assert set(res["seen"]["torque"]["per_task"]) <= {"walk", "stand", "jump_in_place", "cut"}
    assert set(res["unseen"]["torque"]["per_task"]) == {"squat", "run"}
    assert res["physics"]["positive_definite"] is True
    assert "torque MSE" in r.stdout and "cond(H)" in r.stdout


def test_config_object_is_not_overridden_by_defaults(tiny, tmp_path):
    rd = train(tiny, config={"method": "mlp", "lim": False, "epochs": 1, "batch_size": 4096}, out=tmp_path / "r",
               progress=False)
    spec = json.loads((rd / "model.json").read_text())
    assert spec["method"] == "mlp" and spec["lim"] is False
    conf = TrainConfig.from_dict(json.loads((rd / "config.json").read_text()))
    assert conf.batch_size == 4096 and conf.epochs == 1


def test_early_stopping_keeps_the_best_validation_epoch_of_training_users_only(split, tmp_path):
    """patience 1 with a learning rate that makes the validation loss worsen: the run stops early, keeps the best
    epoch's weights (the last epoch's stay as final_model), and the validation users are training users."""
    rd = train(list(split.train), "exolan", epochs=12, seed=0, out=tmp_path / "es", progress=False,
               batch_size=1024, threads=1, lr=0.05, patience=1, val_users=2, val_every=0)
    run = json.loads((rd / "run.json").read_text())
    rows = [json.loads(x) for x in (rd / "metrics.jsonl").read_text().splitlines()]
    best = min(range(len(rows)), key=lambda i: rows[i]["val_loss"])
    assert run["best_epoch"] == best + 1
    assert run["epochs"] == len(rows) and (run["stopped_early"] == (len(rows) < 12))
    if run["stopped_early"]:
        assert len(rows) == best + 2                    # one epoch without improvement, then stop
    train_users = {t.subject for t in split.train}
    assert set(run["val_users"]) <= train_users and len(run["val_users"]) == 2
    assert not set(run["val_users"]) & {t.subject for t in split.test_seen}
    ck = torch.load(rd / "checkpoint.pt", weights_only=False)
    model, _ = load_run(rd)
    assert all(torch.equal(v, ck["model"][k]) for k, v in model.state_dict().items())
    if run["best_epoch"] != run["epochs"]:
        assert any(not torch.equal(ck["final_model"][k], ck["model"][k]) for k in ck["model"])
    # resuming a stopped run trains nothing more
    train(list(split.train), "exolan", epochs=12, seed=0, out=rd, resume=True, progress=False,
          batch_size=1024, threads=1, lr=0.05, patience=1, val_users=2, val_every=0)
    assert len((rd / "metrics.jsonl").read_text().splitlines()) == len(rows)


def test_increment_normalisation_weighs_the_motion_within_the_horizon(tiny):
    from exolan.train import ms_weights

    trials = list(tiny)
    stats = compute_stats(trials, horizon=4)
    w_q, w_qd = ms_weights(TrainConfig(w_fd=0.01, w_ms=1.0, ms_norm="increment"), stats, "cpu")
    assert w_q.shape == (4, 2) and w_qd.shape == (4, 2)
    t = trials[0]
    v = t.valid[2:] & t.valid[:-2]
    assert w_qd[1, 0].item() == pytest.approx(1 / np.concatenate(
        [(x.qd[2:] - x.qd[:-2])[x.valid[2:] & x.valid[:-2]] for x in trials])[:, 0].var(), rel=1e-5)
    assert v.any()
    # the motion grows with the horizon, so the weights fall
    assert torch.all(w_q[1:] < w_q[:-1]) and torch.all(w_qd[1:] < w_qd[:-1])
    sq, sqd = ms_weights(TrainConfig(w_fd=0.01, w_ms=1.0), stats, "cpu")
    assert sq.shape == (2,) and torch.allclose(sq, 1 / torch.tensor(stats["var_q"], dtype=torch.float32))
    with pytest.raises(ValueError, match="ms_norm"):
        TrainConfig(ms_norm="other")
    with pytest.raises(ValueError, match="val_users"):
        TrainConfig(patience=3)
