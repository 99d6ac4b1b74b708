"""Export to the engine's weight file: names, dtypes, shapes and metadata follow DESIGN.md section 3; the CLI
exports a trained run and `exolan rollout` runs it; the engine refuses what it cannot run."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from safetensors import safe_open

from exolan import Engine
from exolan.export import export
from exolan.models import build_model

CHANNELS = ["q_hip", "q_knee", "qd_hip", "qd_knee", "f_v", "cop_x", "cop_z"]


@pytest.mark.parametrize("method,lim", [("exolan", True), ("delan-lstm", False), ("delan", True)])
def test_file_holds_every_weight_in_float64_with_metadata(tmp_path, method, lim):
    m = build_model(method, lim=lim, context_channels=CHANNELS, joint_names=("hip", "knee"), v_scale=3.5)
    path = export(m, tmp_path / "m.safetensors", {"dt": 0.005, "train_note": "test"})
    sd = m.state_dict()
    with safe_open(str(path), "np") as f:
        assert set(f.keys()) == set(sd)
        for k in f.keys():
            a = f.get_tensor(k)
            assert a.dtype == np.float64, k
            assert a.shape == tuple(sd[k].shape), k
            np.testing.assert_array_equal(a, sd[k].double().numpy())
        md = f.metadata()
    assert md["format"] == "exolan-weights" and md["format_version"] == "1"
    assert md["method"] == method and md["lim"] == ("true" if lim else "false")
    assert json.loads(md["joint_types"]) == ["revolute", "revolute"]
    assert json.loads(md["joint_names"]) == ["hip", "knee"]
    assert md["encoder"] == {"exolan": "tcn", "delan-lstm": "lstm", "delan": "none"}[method]
    assert float(md["v_scale"]) == 3.5 and float(md["dt"]) == 0.005
    assert md["train_note"] == "test" and md["activation"] == "tanh"
    for key in ("z_dim", "context_channels", "tcn_levels", "tcn_kernel", "lstm_layers", "hidden", "lim_hidden",
                "softplus_offset", "lim_scale", "coulomb_eps"):
        assert key in md, key
    eng = Engine(path)
    assert (eng.method, eng.lim, eng.joint_names, eng.dt) == (method, lim, ["hip", "knee"], 0.005)


def test_black_box_methods_are_refused(tmp_path):
    m = build_model("mlp-tcn", lim=True, context_channels=CHANNELS)
    with pytest.raises(ValueError, match="black box"):
        export(m, tmp_path / "x.safetensors")


def test_engine_rejects_a_renamed_or_reshaped_tensor(tmp_path):
    from safetensors.numpy import load_file, save_file

    m = build_model("delan", lim=False)
    path = export(m, tmp_path / "m.safetensors")
    with safe_open(str(path), "np") as f:
        md = f.metadata()
    t = load_file(str(path))
    t["delan.L.1.weigth"] = t.pop("delan.L.1.weight")
    save_file(t, str(tmp_path / "typo.safetensors"), metadata=md)
    with pytest.raises(ValueError, match="delan.L.1.weight"):
        Engine(tmp_path / "typo.safetensors")
    t = load_file(str(path))
    t["delan.V.2.weight"] = t["delan.V.2.weight"][:, :10]
    save_file(t, str(tmp_path / "shape.safetensors"), metadata=md)
    with pytest.raises(ValueError, match="delan.V.2.weight"):
        Engine(tmp_path / "shape.safetensors")
    t = load_file(str(path))
    t["delan.V.2.bias"] = t["delan.V.2.bias"].astype(np.float32)
    save_file(t, str(tmp_path / "f32.safetensors"), metadata=md)
    with pytest.raises(ValueError, match="F32"):
        Engine(tmp_path / "f32.safetensors")
    save_file(load_file(str(path)), str(tmp_path / "v2.safetensors"), metadata={**md, "format_version": "2"})
    with pytest.raises(ValueError, match="version"):
        Engine(tmp_path / "v2.safetensors")


def test_cli_export_and_rollout_of_a_trained_run(small_world, tmp_path):
    from exolan.data import load, paper_split
    from exolan.train import load_run, train

    split = paper_split(load(small_world))
    users = sorted({t.subject for t in split.train})[:2]
    tiny = split.train.select(subjects=users, tasks={"walk"})
    run = train(tiny, "exolan", epochs=1, seed=0, out=tmp_path / "run", progress=False, threads=1)
    out = tmp_path / "model.safetensors"
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "export", str(run), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "exported" in r.stdout
    eng = Engine(out)
    model, meta = load_run(run)
    assert eng.dt == pytest.approx(meta["dt"])
    assert eng.metadata["train_epoch"] == "1"
    # the exported weights are the run's (float32 values carried exactly in float64)
    with safe_open(str(out), "np") as f:
        np.testing.assert_array_equal(f.get_tensor("delan.L.0.weight"),
                                      model.state_dict()["delan.L.0.weight"].double().numpy())
    res_path = tmp_path / "rollout.json"
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "rollout", str(out), "--data", str(small_world),
                        "--horizon", "10", "--out", str(res_path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    res = json.loads(res_path.read_text())
    assert res["rollouts"] > 100 and res["horizon"] == 10
    assert set(res["q_rmse"]) == {"hip", "knee"}
    assert all(np.isfinite(v) for v in res["q_rmse"].values())
