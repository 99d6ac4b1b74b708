import sys, numpy as np
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare, exo_copy
from exolan.diagnose.limits import rate_per_trial
root = sys.argv[1]
flat = prepare(load_trials(root), max_delay=0.1, seed=0)
q = flat.q.double().numpy(); qd = flat.qd.double().numpy(); qdd = flat.qdd.double().numpy() if hasattr(flat, "qdd") else None
train = (~flat.held & flat.valid).numpy(); held = (flat.held & flat.valid).numpy()
for j, nm in enumerate(flat.joints):
    te = flat.tau_e[:, j].double().numpy()
    own = te - exo_copy(flat, j).tau_e[:, j].double().numpy()
    x = np.nan_to_num(rate_per_trial(own, flat))
    feats = [np.ones(len(x))]
    for k in range(q.shape[1]):
        feats += [q[:, k], qd[:, k], np.cos(q[:, k]), np.sin(q[:, k]), qd[:, k] ** 2, qd[:, k] * np.cos(q[:, k])]
        if qdd is not None: feats += [qdd[:, k], qdd[:, k] * np.cos(q[:, k])]
    F = np.stack(feats, 1)
    start, pred = 0, np.zeros_like(x)
    for T in flat.lengths:
        sl = slice(start, start + T); tr = train[sl]
        c = np.linalg.lstsq(F[sl][tr], x[sl][tr], rcond=None)[0]
        pred[sl] = F[sl] @ c; start += T
    share = 1 - np.mean((x - pred)[held] ** 2) / np.mean(x[held] ** 2)
    print(nm, "held-out share of the own-variation rate predictable from motion:", round(share, 3), "qdd" if qdd is not None else "no qdd")
