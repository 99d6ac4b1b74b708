"""The dataset reader: round trip, bad input, NaN masking, cache, layout 2, splits, real recordings."""
from __future__ import annotations

import json
import shutil
import stat
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from exolan.data import (PAPER_TRAIN_TASKS, DataError, DataWarning, Trial, context_channels, context_features, load,
                         paper_split, savgol_derivative, savgol_window, stack)
from exolan.world import make_users, simulate, simulate_trial


def _copy(world: Path, dst: Path, subjects=("S01", "S02"), tasks=("walk",)) -> Path:
    dst.mkdir()
    lines = world.joinpath("subjects.csv").read_text().splitlines()
    dst.joinpath("subjects.csv").write_text("\n".join([lines[0]] + [l for l in lines[1:] if l.split(",")[0] in subjects]) + "\n")
    for s in subjects:
        for t in tasks:
            shutil.copytree(world / s / f"{t}_1_1", dst / s / f"{t}_1_1")
    return dst


def _edit_csv(path: Path, fn):
    lines = path.read_text().splitlines()
    path.write_text("\n".join(fn(lines)) + "\n")


def test_round_trip_noise_free(tmp_path):
    simulate(tmp_path, users=2, tasks=["walk", "squat"], seconds=3, seed=4, noise=False, progress=False)
    ds = load(tmp_path, cache=False)
    assert len(ds) == 2 * 2 * 2 and ds.layout == 1
    users = make_users(2, np.random.default_rng(np.random.SeedSequence([4, 0])))
    for tr in ds:
        assert isinstance(tr, Trial) and tr.joints == ("hip", "knee") and tr.dt == pytest.approx(0.005)
        u = users[int(tr.subject[1:]) - 1]
        assert tr.mass == u.mass
        _, _, truth = simulate_trial(u, tr.task, 3, seed=4, noise=False)
        s = "lr".index(tr.side)
        np.testing.assert_allclose(tr.q, truth["q"][:, s], atol=1e-13)
        np.testing.assert_allclose(tr.qd, truth["qd"][:, s], atol=1e-12)
        np.testing.assert_allclose(tr.tau, truth["tau_h"][:, s] + truth["tau_e_rec"][:, s], atol=1e-9)
        np.testing.assert_allclose(tr.tau_e, truth["tau_e_rec"][:, s], atol=1e-12)
        np.testing.assert_allclose(tr.f_v, truth["fy"][:, s], atol=1e-9)
        swing = truth["fy"][:, s] <= 0
        assert np.isnan(tr.cop[swing]).all() and np.isfinite(tr.cop[~swing]).all()
        # Savitzky-Golay acceleration against the analytic one (interior samples)
        err = tr.qdd[10:-10] - truth["qdd"][10:-10, s]
        assert np.sqrt(np.mean(err ** 2)) < 0.03 * np.sqrt(np.mean(truth["qdd"][10:-10, s] ** 2)) + 0.05
        assert tr.valid[5:-5].all()


def test_small_world_loads_and_splits(small_world):
    ds = load(small_world)
    assert ds.subjects == [f"S0{i}" for i in range(1, 7)]
    assert len(ds) == 6 * 6 * 2
    sp = paper_split(ds)
    assert {t.subject for t in sp.train} == {"S01", "S02", "S03", "S04"}
    assert {t.subject for t in sp.test_seen} == {"S05", "S06"} == {t.subject for t in sp.test_unseen}
    assert {t.task for t in sp.train} == {"walk", "stand", "jump_in_place", "cut"} <= set(PAPER_TRAIN_TASKS)
    assert {t.task for t in sp.test_unseen} == {"squat", "run"}
    flat = stack(sp.train.trials)
    n = sum(len(t) for t in sp.train)
    assert flat["q"].shape == (n, 2) and flat["subject_idx"].shape == (n,)
    k = 5
    tr = sp.train[k]
    sel = flat["trial_idx"] == k
    np.testing.assert_array_equal(flat["tau"][sel], tr.tau)
    assert flat["subjects"][flat["subject_idx"][sel][0]] == tr.subject
    assert flat["tasks"][flat["task_idx"][sel][0]] == tr.task


def test_context_features_gate_the_cop(small_world):
    ds = load(small_world)
    tr = next(t for t in ds if t.task == "walk")
    x = context_features(tr)
    assert context_channels(tr) == ["q_hip", "q_knee", "qd_hip", "qd_knee", "f_v", "cop_x", "cop_z"]
    assert x.shape == (len(tr), 7)
    swing = tr.f_v <= 20
    assert swing.any() and (~swing).any()
    assert (x[swing, 5:] == 0).all() and np.isfinite(x).all()
    np.testing.assert_array_equal(x[~swing, 5:], tr.cop[~swing])


def _tree(root: Path) -> dict:
    """Every path under root (hidden ones included) with its size and modification time."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


def test_second_load_comes_from_the_cache_and_changes_invalidate_it(small_world, tmp_path, monkeypatch):
    root = _copy(small_world, tmp_path / "w", tasks=("walk", "run"))
    monkeypatch.setenv("EXOLAN_CACHE_DIR", str(tmp_path / "cache"))
    t0 = time.perf_counter()
    a = load(root)
    t_cold = time.perf_counter() - t0
    assert len(list((tmp_path / "cache").glob("dataset-*.pkl"))) == 1
    t0 = time.perf_counter()
    b = load(root)
    t_warm = time.perf_counter() - t0
    assert t_warm < t_cold
    np.testing.assert_array_equal(a[0].tau, b[0].tau)
    # a changed file gives a different dataset, not a stale cache
    _edit_csv(root / "subjects.csv", lambda ls: [ls[0]] + [l.replace(l.split(",")[1], "99.0") if l.startswith("S01") else l for l in ls[1:]])
    c = load(root)
    assert next(t for t in c if t.subject == "S01").mass == 99.0
    assert len(list((tmp_path / "cache").glob("dataset-*.pkl"))) == 2


def test_the_data_folder_never_receives_a_file(small_world, tmp_path, monkeypatch):
    """A read-only (or shared, or version-controlled) data folder is read and left as it was: the cache goes
    to the user's cache folder (here the default one, EXOLAN_CACHE_DIR unset). Root ignores the read-only bit,
    so the folder's listing is compared too."""
    root = _copy(small_world, tmp_path / "ro")
    monkeypatch.delenv("EXOLAN_CACHE_DIR")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    before = _tree(root)
    dirs = [root] + [p for p in root.rglob("*") if p.is_dir()]
    modes = {d: d.stat().st_mode for d in dirs}
    for d in dirs:
        d.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP)
    try:
        a = load(root)
        b = load(root)  # from the cache
        assert len(a) == len(b) == 4
        np.testing.assert_array_equal(a[0].q, b[0].q)
        assert _tree(root) == before
        assert len(list((tmp_path / "cache" / "exolan").glob("dataset-*.pkl"))) == 1
    finally:
        for d in reversed(dirs):
            d.chmod(modes[d])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the Linux cache folder (XDG)")
def test_the_default_cache_is_the_users_cache_folder(small_world, tmp_path, monkeypatch):
    """Without EXOLAN_CACHE_DIR: $XDG_CACHE_HOME/exolan, else ~/.cache/exolan (Linux)."""
    import exolan.data as data

    root = _copy(small_world, tmp_path / "w")
    monkeypatch.delenv("EXOLAN_CACHE_DIR")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert data.cache_dir() == tmp_path / "xdg" / "exolan"
    load(root)
    assert list((tmp_path / "xdg" / "exolan").glob("dataset-*.pkl"))
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert data.cache_dir() == tmp_path / "home" / ".cache" / "exolan"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/dir")  # invalid per the XDG spec: ignored
    assert data.cache_dir() == tmp_path / "home" / ".cache" / "exolan"
    assert not [p for p in root.rglob("*") if p.name.startswith(".")]


def test_an_unwritable_cache_folder_does_not_stop_loading(small_world, tmp_path, monkeypatch):
    root = _copy(small_world, tmp_path / "w")
    before = _tree(root)
    (tmp_path / "file").write_text("x")
    monkeypatch.setenv("EXOLAN_CACHE_DIR", str(tmp_path / "file" / "cache"))  # under a file: never creatable
    assert len(load(root)) == 4
    assert _tree(root) == before


def test_extra_columns_are_ignored(small_world, tmp_path):
    root = _copy(small_world, tmp_path / "w")
    p = root / "S01" / "walk_1_1" / "Exo.csv"
    _edit_csv(p, lambda ls: [ls[0] + ",thigh_imu_l_gyro_x,notes"] + [l + ",0.1,x" for l in ls[1:]])
    ds = load(root, cache=False)
    assert len(ds) == 4


@pytest.mark.parametrize("case", ["missing_column", "nonuniform_time", "unknown_mass", "radians_angles",
                                  "radians_both", "empty", "header_only", "text_cell", "moment_time"])
def test_bad_input_names_file_and_column(small_world, tmp_path, case, monkeypatch):
    root = _copy(small_world, tmp_path / "w")
    monkeypatch.setenv("EXOLAN_CACHE_DIR", str(tmp_path / "cache"))
    exo = root / "S02" / "walk_1_1" / "Exo.csv"
    mom = root / "S02" / "walk_1_1" / "Joint_Moments_Filt.csv"
    if case == "missing_column":
        def drop(ls, name="knee_angle_r"):
            i = ls[0].split(",").index(name)
            return [",".join(c for k, c in enumerate(l.split(",")) if k != i) for l in ls]
        _edit_csv(exo, drop)
        expect = ["Exo.csv", "knee_angle_r"]
    elif case == "nonuniform_time":
        # time going backwards (jitter and dropped samples are read: `test_irregular_time_stamps_...`)
        _edit_csv(exo, lambda ls: ls[:100] + [ls[100].replace(ls[100].split(",")[0], "0.3", 1)] + ls[101:])
        expect = ["Exo.csv", "time", "row 100", "not increasing"]
    elif case == "unknown_mass":
        _edit_csv(root / "subjects.csv", lambda ls: [l for l in ls if not l.startswith("S02")])
        expect = ["subjects.csv", "S02", "mass"]
    elif case in ("radians_angles", "radians_both"):
        cols = exo.read_text().splitlines()[0].split(",")

        def to_rad(ls):
            out = [ls[0]]
            for l in ls[1:]:
                v = l.split(",")
                for k, c in enumerate(cols):
                    if c.endswith(("_angle_l", "_angle_r")) or (case == "radians_both" and c.endswith("_velocity_filt")):
                        v[k] = repr(float(np.radians(float(v[k]))))
                out.append(",".join(v))
            return out
        _edit_csv(exo, to_rad)
        expect = ["Exo.csv", "radians", "_angle_"]
    elif case == "empty":
        exo.write_text("")
        expect = ["Exo.csv", "empty"]
    elif case == "header_only":
        _edit_csv(mom, lambda ls: ls[:1])
        expect = ["Joint_Moments_Filt.csv", "empty"]
    elif case == "text_cell":
        _edit_csv(mom, lambda ls: ls[:50] + [",".join(ls[50].split(",")[:2] + ["oops"] + ls[50].split(",")[3:])] + ls[51:])
        expect = ["Joint_Moments_Filt.csv", "knee_angle_l_moment", "row 50"]
    elif case == "moment_time":
        _edit_csv(mom, lambda ls: ls[:-10])
        expect = ["Joint_Moments_Filt.csv", "time"]
    with pytest.raises(DataError) as ei:
        load(root)
    msg = str(ei.value)
    for e in expect:
        assert e in msg, (e, msg)
    assert isinstance(ei.value, ValueError)
    assert not list((tmp_path / "cache").glob("dataset-*.pkl"))  # a refused dataset is not cached


def test_nan_gaps_are_masked_not_zero_filled(small_world, tmp_path):
    root = _copy(small_world, tmp_path / "w")
    mom = root / "S01" / "walk_1_1" / "Joint_Moments_Filt.csv"
    _edit_csv(mom, lambda ls: ls[:201] + [l.split(",")[0] + ",,,," for l in ls[201:241]] + ls[241:])
    exo = root / "S01" / "walk_1_1" / "Exo.csv"
    cols = exo.read_text().splitlines()[0].split(",")
    blank = {cols.index("hip_angle_l"), cols.index("hip_angle_l_velocity_filt")}
    _edit_csv(exo, lambda ls: ls[:401] + [",".join("" if k in blank else c for k, c in enumerate(l.split(",")))
                                          for l in ls[401:411]] + ls[411:])
    ds = load(root, cache=False)
    tr = next(t for t in ds if t.subject == "S01" and t.side == "l")
    assert np.isnan(tr.tau[200:240]).all() and not tr.valid[200:240].any()
    assert tr.valid[100:199].all()
    assert np.isnan(tr.q[400:410, 0]).all() and not tr.valid[400:410].any()
    assert np.isnan(tr.qdd[400:410, 0]).all() and np.isfinite(tr.qdd[400:410, 1]).all()
    assert tr.valid[380:395].all() and tr.valid[415:430].all()   # Savitzky-Golay per finite stretch
    assert not (tr.tau[200:240] == 0).any()


def test_failed_simulation_leaves_nothing_half_written(tmp_path, monkeypatch):
    """A run that fails half-way leaves the previous world untouched and no temporary files."""
    import exolan.world as world

    out = tmp_path / "w"
    simulate(out, users=1, tasks=["stand"], seconds=1, progress=False)
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    calls = {"n": 0}
    real = world.record

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("boom")
        return real(*a, **k)

    monkeypatch.setattr(world, "record", failing)
    with pytest.raises(RuntimeError):
        simulate(out, users=2, tasks=["walk", "stand"], seconds=1, progress=False)
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert [p.name for p in tmp_path.iterdir()] == ["w"]
    # a successful run replaces the old world completely (no stale subjects)
    monkeypatch.setattr(world, "record", real)
    simulate(out, users=2, tasks=["walk"], seconds=1, progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["S01", "S02", "effects.json", "subjects.csv"]
    assert [p.name for p in (out / "S01").iterdir()] == ["walk_1_1"]
    assert [p.name for p in tmp_path.iterdir()] == ["w"]
    # a directory that is not a world is never replaced
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    with pytest.raises(ValueError, match="not a simulated world"):
        simulate(other, users=1, tasks=["walk"], seconds=1, progress=False)
    assert (other / "notes.txt").read_text() == "keep"


def test_layout2_prismatic_and_revolute(tmp_path):
    t = np.arange(600) * 0.002
    x = 0.1 * np.sin(2 * np.pi * 1.5 * t)
    th = 0.8 * np.cos(2 * np.pi * 0.7 * t)
    cols = {"time": t, "q_slide": x, "q_arm": th, "tau_slide": 5 * x, "tau_arm": np.sin(th)}
    lines = [",".join(cols)] + [",".join(repr(float(v)) for v in row) for row in zip(*cols.values())]
    (tmp_path / "bench.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "bench.json").write_text(json.dumps({"joints": [{"name": "slide", "type": "prismatic"},
                                                                {"name": "arm", "type": "revolute"}],
                                                     "units": {"q": "m", "tau": "N"}}))
    ds = load(tmp_path / "bench.csv")
    assert ds.layout == 2 and len(ds) == 1
    tr = ds[0]
    assert tr.joint_types == ("prismatic", "revolute") and tr.side == "" and tr.mass == 1.0
    assert tr.dt == pytest.approx(0.002)
    xd = 0.1 * 2 * np.pi * 1.5 * np.cos(2 * np.pi * 1.5 * t)
    # interior samples: within half a window (55 ms: 14 samples at 500 Hz) of an end the filter extrapolates
    np.testing.assert_allclose(tr.qd[15:-15, 0], xd[15:-15], rtol=0, atol=1e-4)
    xdd = -0.1 * (2 * np.pi * 1.5) ** 2 * np.sin(2 * np.pi * 1.5 * t)
    np.testing.assert_allclose(tr.qdd[30:-30, 0], xdd[30:-30], atol=2e-3)
    assert context_channels(tr) == ["q_slide", "q_arm", "qd_slide", "qd_arm"]
    assert context_features(tr).shape == (600, 4)
    assert (tr.f_v == 0).all() and tr.valid[10:-10].all()
    # the directory form finds the same recording
    assert len(load(tmp_path)) == 1
    (tmp_path / "bench.json").unlink()
    with pytest.raises(DataError, match="bench.json"):
        load(tmp_path / "bench.csv")


def test_derivative_window_spans_the_same_time_at_any_sample_rate(tmp_path):
    """The Savitzky-Golay window is 55 ms at every rate (the paper's 11 samples at 200 Hz). A 1 kHz bench
    recording without velocities, 14-bit encoder: with an 11-sample window q̈'s error was 16 % of its RMS."""
    assert [savgol_window(1 / f) for f in (200, 1000, 100, 50)] == [11, 55, 5, 5]
    with pytest.raises(ValueError, match="sample time"):
        savgol_window(0.0)
    rng = np.random.default_rng(5)
    dt = 0.001
    t = np.arange(20000) * dt
    q, qdd = np.zeros_like(t), np.zeros_like(t)
    for _ in range(6):
        a, w, p = rng.uniform(0.1, 0.4), 2 * np.pi * rng.uniform(0.2, 3.0), rng.uniform(0, 2 * np.pi)
        q += a * np.sin(w * t + p)
        qdd -= a * w * w * np.sin(w * t + p)
    step = 2 * np.pi / 2 ** 14
    cols = {"time": t, "q_axis": np.round(q / step) * step, "tau_axis": 0.01 * qdd}
    lines = [",".join(cols)] + [",".join(repr(float(v)) for v in row) for row in zip(*cols.values())]
    (tmp_path / "bench.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "bench.json").write_text(json.dumps({"joints": [{"name": "axis", "type": "revolute"}]}))
    tr = load(tmp_path / "bench.csv")[0]
    inner = slice(100, -100)
    err = np.sqrt(np.mean((tr.qdd[inner, 0] - qdd[inner]) ** 2)) / qdd.std()
    assert err < 0.03, err
    fixed = savgol_derivative(savgol_derivative(cols["q_axis"][:, None], dt, window=11), dt, window=11)[:, 0]
    assert np.sqrt(np.mean((fixed[inner] - qdd[inner]) ** 2)) / qdd.std() > 3 * err


def test_irregular_time_stamps_are_resampled_and_dropped_samples_masked(tmp_path):
    """A logger on a PC clock: time stamps with 10 % jitter and 7 dropped samples. The reader resamples onto
    the median step, marks the gap NaN (invalid), and says so; a repeated time stamp is an error."""
    rng = np.random.default_rng(2)
    dt = 0.002
    t = np.arange(1500) * dt + rng.uniform(-0.1, 0.1, 1500) * dt
    keep = np.ones(1500, bool)
    keep[700:707] = False
    t = t[keep]
    q = 0.5 * np.sin(2 * np.pi * 1.1 * t)
    cols = {"time": t, "q_arm": q, "tau_arm": 2.0 * q}
    lines = [",".join(cols)] + [",".join(repr(float(v)) for v in row) for row in zip(*cols.values())]
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "log.json").write_text(json.dumps({"joints": [{"name": "arm", "type": "revolute"}]}))
    with pytest.warns(DataWarning, match="not uniformly sampled.*1 gap"):
        tr = load(tmp_path / "log.csv", cache=False)[0]
    assert tr.dt == pytest.approx(dt, rel=0.01)
    grid = t[0] + np.arange(len(tr.q)) * tr.dt
    ok = np.isfinite(tr.q[:, 0])
    # linear interpolation between jittered samples: error ~ (step/2)² q̈ / 2
    np.testing.assert_allclose(tr.q[ok, 0], 0.5 * np.sin(2 * np.pi * 1.1 * grid[ok]), atol=2e-4)
    gap = (grid > t[699] + 1e-9) & (grid < t[700] - 1e-9)
    assert gap.sum() >= 6 and not ok[gap].any() and ok[~gap].all()
    assert not tr.valid[gap].any() and tr.valid[100:600].all()
    # velocities from q: per finite stretch, accurate on both sides of the gap
    w = 1.1 * 2 * np.pi
    inner = np.r_[100:600, 800:1300]
    np.testing.assert_allclose(tr.qd[inner, 0], 0.5 * w * np.cos(w * grid[inner]), atol=0.02 * 0.5 * w)
    t2 = t.copy()
    t2[50] = t2[49]
    lines = [",".join(cols)] + [",".join(repr(float(v)) for v in row) for row in zip(t2, q, 2.0 * q)]
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="row 51.*repeats"):
        load(tmp_path / "log.csv", cache=False)


def test_a_time_column_in_milliseconds_is_read_when_declared_and_flagged_when_not(tmp_path):
    t = np.arange(400) * 2.0                                   # ms: 500 Hz
    q = 0.3 * np.sin(2 * np.pi * 1.0 * t / 1000.0)
    lines = ["time,q_arm,tau_arm"] + [f"{a:.6g},{b:.9g},{2 * b:.9g}" for a, b in zip(t, q)]
    (tmp_path / "ms.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "ms.json").write_text(json.dumps({"joints": [{"name": "arm"}], "units": {"time": "ms"}}))
    assert load(tmp_path / "ms.csv", cache=False)[0].dt == pytest.approx(0.002)
    (tmp_path / "ms.json").write_text(json.dumps({"joints": [{"name": "arm"}]}))
    with pytest.warns(DataWarning, match="milliseconds"):
        load(tmp_path / "ms.csv", cache=False)
    (tmp_path / "ms.json").write_text(json.dumps({"joints": [{"name": "arm"}], "units": {"time": "min"}}))
    with pytest.raises(DataError, match="units.time"):
        load(tmp_path / "ms.csv", cache=False)


def test_the_cli_reports_bad_input_without_a_traceback(tmp_path, capsys):
    """`exolan diagnose` on recordings it cannot use: exit 2 and one line naming the problem."""
    from exolan.cli import main

    assert main(["diagnose", str(tmp_path / "nothing"), "--out", str(tmp_path / "d")]) == 2
    assert "no such file" in capsys.readouterr().err
    for name, fs in (("a", 1000), ("b", 500)):        # two recordings of one bench at different rates
        t = np.arange(300) / fs
        lines = ["time,q_x,tau_x"] + [f"{a:.6g},{np.sin(a):.6g},{np.cos(a):.6g}" for a in t]
        (tmp_path / f"{name}.csv").write_text("\n".join(lines) + "\n")
        (tmp_path / f"{name}.json").write_text(json.dumps({"joints": [{"name": "x"}]}))
    assert main(["diagnose", str(tmp_path), "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "sample time differ" in err and "Traceback" not in err


def test_missing_path_and_unknown_layout(tmp_path):
    with pytest.raises(DataError, match="no such"):
        load(tmp_path / "nope")
    (tmp_path / "S01" / "walk_1_1").mkdir(parents=True)
    (tmp_path / "S01" / "walk_1_1" / "Exo.csv").write_text("time\n0\n")
    with pytest.raises(DataError, match="subjects.csv"):
        load(tmp_path)


def test_real_recordings_load(real_data):
    ds = load(real_data)
    assert ds.subjects == ["REAL01", "REAL02", "REAL03", "REAL04", "REAL05"]
    assert np.isnan(ds.heights["REAL05"]) and ds.masses["REAL05"] == 67.2
    # REAL05's left side was never measured: left out, and said so
    assert [k for k, _ in ds.skipped] == ["REAL05/walk_treadmill_1_1/l"]
    assert len(ds) == 2 * 28 - 1
    for tr in ds:
        assert tr.valid.any()
        assert np.isnan(tr.tau[~tr.valid]).any(axis=1).all() or not np.isfinite(tr.qdd[~tr.valid]).all() \
            or not np.isfinite(tr.q[~tr.valid]).all() or not np.isfinite(tr.f_v[~tr.valid]).all()
        assert (tr.tau_e == 0).all()          # nobody wore an exoskeleton
        swing = tr.f_v < 50
        assert np.isnan(tr.cop[swing]).all()  # CoP undefined in swing
        x = context_features(tr)
        assert np.isfinite(x[tr.valid, :5]).all()
    sts = next(t for t in ds if t.name == "sit_to_stand_1_1" and t.side == "r")
    assert 0.4 < sts.valid.mean() < 0.7        # hip moments masked while seated
    walk = next(t for t in ds if t.subject == "REAL04" and t.side == "r")
    assert -1.0 < np.nanmin(walk.tau[:, 1]) / walk.mass < -0.3
    sp = paper_split(ds)
    assert {t.subject for t in sp.test_seen} | {t.subject for t in sp.test_unseen} <= {"REAL04", "REAL05"}


def _rewrite_columns(path: Path, fn):
    lines = path.read_text().splitlines()
    cols = lines[0].split(",")
    out = [lines[0]]
    for l in lines[1:]:
        v = l.split(",")
        for k, c in enumerate(cols):
            nv = fn(c, float(v[0]), v[k])
            if nv is not None:
                v[k] = nv
        out.append(",".join(v))
    path.write_text("\n".join(out) + "\n")


def test_small_standing_angles_in_degrees_are_not_mistaken_for_radians(small_world, tmp_path):
    """Standing still in degrees (all within +-3 deg, velocity noise a few deg/s) is legal."""
    root = _copy(small_world, tmp_path / "w", tasks=("walk", "stand"))

    def still(c, t, v):
        if c.endswith(("_angle_l", "_angle_r")):
            return repr(float(2.5 * np.sin(2 * np.pi * 0.5 * t)))
        if c.endswith("_velocity_filt"):
            return repr(float(2.5 * np.pi * np.cos(2 * np.pi * 0.5 * t)))
        return None
    _rewrite_columns(root / "S01" / "stand_1_1" / "Exo.csv", still)
    ds = load(root, cache=False)
    assert len(ds) == 8


def test_a_dataset_entirely_in_radians_is_refused(small_world, tmp_path):
    root = _copy(small_world, tmp_path / "w", tasks=("walk", "stand"))
    to_rad = lambda c, t, v: repr(float(np.radians(float(v)))) if c.endswith(  # noqa: E731
        ("_angle_l", "_angle_r", "_velocity_filt")) else None
    for p in root.rglob("Exo.csv"):
        _rewrite_columns(p, to_rad)
    with pytest.raises(DataError, match=r"walk_1_1/Exo.csv: column '\w+_angle_\w' looks like radians"):
        load(root)


def test_task_groups():
    from exolan.data import task_group

    assert task_group("walk") == "cyclic" and task_group("push_pull") == "impedance"
    assert task_group("cut") == "unstructured" and task_group("walk_treadmill") == "cyclic"
    assert task_group("drop_jump_asym") == "unstructured" and task_group("sit_to_stand_weak_legs") == "impedance"
    assert task_group("juggling") == "unknown"
