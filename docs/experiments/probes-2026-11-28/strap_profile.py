"""Profile the knee strap's compliance exactly (base columns at q - c*tau_e), against the linearised column."""
import sys, copy, numpy as np, warnings
warnings.simplefilter("ignore")
from exolan.diagnose import physics, ident
from exolan.diagnose.procedure import load_trials
from exolan.diagnose.flat import prepare
from exolan.diagnose.settings import Settings
s = Settings()
flat = prepare(load_trials(sys.argv[1]), max_delay=s.max_delay, seed=s.seed)
j = flat.joints.index("knee")
phys = physics.setup(flat, s.effects, [j], alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
prob = phys._probs[j]
f_lin = prob.fit(["strap_compliance"])
print("linearised: k", 1 / f_lin.est["strap_compliance"])
sig = prob.sig
def rss(c):
    sg = copy.copy(sig)
    sg.q = sig.q.copy(); sg.qd = sig.qd.copy(); sg.qdd = sig.qdd.copy()
    sg.q[:, j] -= c * sig.tau_e[:, j]; sg.qd[:, j] -= c * sig.tau_e_d[:, j]; sg.qdd[:, j] -= c * sig.tau_e_dd[:, j]
    X_raw, names = ident.base_columns(sg.q, sg.qd, sg.qdd, sg)
    p = ident.JointProblem(sg, j, sig.lp(X_raw), names, prob.ctx)
    p.train, p.held = prob.train, prob.held
    p.w = prob.w
    f = p.fit([], intervals=False)
    r = (prob.y - f.pred)
    return float(np.sum(prob.w[prob.train] * r[prob.train] ** 2)), float(np.mean(r[prob.held] ** 2))
for k in [float(x) for x in sys.argv[2].split(",")]:
    print(k, *("%.6g" % v for v in rss(1 / k)), flush=True)
print("held base theta (the fixed-term form):")
th = prob.ctx["base_theta"][j]
X0 = prob.ctx["base_raw"]
def rss_held(c):
    q, qd, qdd = sig.q.copy(), sig.qd.copy(), sig.qdd.copy()
    q[:, j] -= c * sig.tau_e[:, j]; qd[:, j] -= c * sig.tau_e_d[:, j]; qdd[:, j] -= c * sig.tau_e_dd[:, j]
    col = np.nan_to_num(sig.lp((ident.base_columns(q, qd, qdd, sig)[0] - X0) @ th))
    return prob.sse([], {}) if c == 0 else _sse_off(col)
def _sse_off(off):
    tr = prob.train; sw = np.sqrt(prob.w[tr])
    rz = prob._partial((prob.y[tr] - off[tr]) * sw)
    return float(rz @ rz)
for k in [float(x) for x in sys.argv[2].split(",")]:
    print(k, "%.6g" % rss_held(1 / k), flush=True)
