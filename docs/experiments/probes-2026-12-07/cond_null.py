"""Probe: rule 3's nulls for a torque gain tested on top of an accepted strap on the same joint, with the strap's
input left alone. The gain term reads the exo torque taken LAG samples in the future (future null) or the
controller's own variation alone (own-variation null), while the strap's deflection keeps the present recorded
torque and its derivatives (passed through the `side` channel, which no backlash term uses here).
Usage: python cond_null.py WORLD JOINT_INDEX"""
import copy, sys, time
import numpy as np, torch
from exolan.diagnose import fit
from exolan.diagnose.candidates import LIBRARY
from exolan.diagnose.export import extend
from exolan.diagnose.flat import exo_own
from exolan.diagnose.nulls import advanced, leak_lag, track_lag
from exolan.diagnose.procedure import load_trials, new_base, reference
from exolan.diagnose.flat import prepare
from exolan.diagnose.refits import refit, held_errors
from exolan.diagnose.rules import paired_gain
from exolan.diagnose.screen import screen
from exolan.diagnose.session import Tools
from exolan.diagnose.settings import Settings
from exolan.diagnose.workers import Workers, running
from exolan.extensions import ExtendedModel

root, j = sys.argv[1], int(sys.argv[2])
s = Settings()
torch.manual_seed(s.seed)
flat = prepare(load_trials(root), max_delay=s.max_delay, seed=s.seed)
t0 = time.time()
w = Workers(2)
with running(w):
    ss, _ = reference(flat, s, None, Tools(), w, [0, 1], new_base(flat, s))
    ss.first_twin.cancel()
print(f"base + reference {time.time() - t0:.0f} s", flush=True)

_gate_kw = fit._gate_kw


def gate_kw(model, f, b):            # the probe's models get the present torque through `side`
    kw = _gate_kw(model, f, b)
    if getattr(model, "_probe", False):
        kw["side"] = (f.side[b], f.side_d[b], f.side_dd[b])
    return kw


fit._gate_kw = gate_kw


def errs(m, f):
    return held_errors(m, f, ss.held, ss.w_held)[1]


def gci(g):
    return f"{g['gain']:.3g} [{g['ci'][0]:.3g}, {g['ci'][1]:.3g}]"


sc = screen(ss.ref, flat, "strap_compliance", j, n_boot=100, seed=s.seed)
init_a = LIBRARY["strap_compliance"].screen_init(sc)
A = extend(ss.base, flat, [("strap_compliance", j)], init=init_a, max_delay=s.max_delay)
refit(A, flat, s)
e_a = errs(A, flat)
print(f"strap alone: k {A.estimate('strap_compliance', j):.4g}, gain over the reference "
      f"{gci(paired_gain(ss.e_ref, e_a, s))}", flush=True)
sg = screen(A, flat, "torque_gain", j, n_boot=100, seed=s.seed)
init_b = dict(init_a, **LIBRARY["torque_gain"].screen_init(sg))
B = extend(ss.base, flat, [("strap_compliance", j), ("torque_gain", j)], init=init_b, max_delay=s.max_delay)
refit(B, flat, s)
e_b = errs(B, flat)
print(f"strap + gain: k {B.estimate('strap_compliance', j):.4g}, gain {B.estimate('torque_gain', j):.4g}; "
      f"on top of the strap {gci(paired_gain(e_a, e_b, s))}", flush=True)


def null(name, tau_gain):
    f = copy.copy(flat)
    f.side, f.side_d, f.side_dd = flat.tau_e, flat.tau_e_d, flat.tau_e_dd     # the strap's present input
    f.tau_e = flat.tau_e.clone()
    f.tau_e[:, j] = tau_gain
    C = extend(ss.base, f, [("strap_compliance", j), ("torque_gain", j)], init=init_b, max_delay=s.max_delay)
    C._probe = True
    C.true_state = lambda q, qd, qdd, a=None, ad=None, add=None, trial=None, side=None: \
        ExtendedModel.true_state(C, q, qd, qdd, side[0], side[1], side[2], trial, None)
    t1 = time.time()
    refit(C, f, s)
    e_c = errs(C, f)
    print(f"{name}: k {C.estimate('strap_compliance', j):.4g}, gain {C.estimate('torque_gain', j):.4g}; over the "
          f"strap alone {gci(paired_gain(e_a, e_c, s))}; the real gain beats it by {gci(paired_gain(e_c, e_b, s))} "
          f"({time.time() - t1:.0f} s)", flush=True)


for lag in sorted({leak_lag(ss.ref, flat, j), track_lag(flat, j)}):
    null(f"gain on the exo torque {lag} samples in the future", advanced(flat, np.eye(flat.n, dtype=int)[j] * lag).tau_e[:, j])
null("gain on the controller's own variation alone", exo_own(flat, j).tau_e[:, j])
