"""How the learned path's fits from scratch size a friction: the recipe as is (unweighted base steps, weighted
refit), weighted from the first step, and the recipe followed by a full weighted schedule."""
import sys, time, copy, functools
import torch
torch.set_num_threads(1)
from exolan.diagnose.settings import Settings
from exolan.diagnose.procedure import load_trials, new_base, fit_base
from exolan.diagnose.flat import prepare
from exolan.diagnose.refits import fresh_fit, refit, FRESH_PIECES
from exolan.diagnose.fit import train
from exolan.diagnose.workers import Workers, running
from exolan.extensions import ExtendedModel

world, effect, j, warm = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
s = Settings()
trials = load_trials(world)
flat = prepare(trials, max_delay=s.max_delay, seed=s.seed)
start = new_base(flat, s)
t0 = time.time()
base, base_start, _ = fit_base(flat, s, None, start)
print(f"base {time.time()-t0:.0f}s", flush=True)
init = {effect: {j: warm}}

def est(m):
    return m.estimate(effect, j)

def as_is():
    m = fresh_fit(flat, s, [(effect, j)], init, base_start)
    return "as is (unweighted base steps + weighted refit)", est(m), m

def weighted_first():
    m = ExtendedModel(copy.deepcopy(base_start), flat.n, [(effect, j)], dt=flat.dt, max_delay=s.max_delay,
                      init=dict(init), coupled_damping=False)
    tr = functools.partial(train, pieces=1)
    tr(m, flat, s.steps_base, lr=s.lr_base, lr_ext=s.lr_ext, batch=s.batch, seed=s.seed, w_acc=s.w_acc, weighted=True)
    refit(m, flat, s, trainer=tr)
    return "weighted from the first step", est(m), m

w = Workers(2)
t0 = time.time()
with running(w):
    outs = w.map([as_is, weighted_first])
for name, e, m in outs:
    print(f"{effect} j{j}: {name}: {e:.4f}", flush=True)
print(f"fits {time.time()-t0:.0f}s")
# then: the as-is model with a further full weighted schedule (the term free)
m = copy.deepcopy(outs[0][2])
t0 = time.time()
train(m, flat, s.steps_base, lr=s.lr_base, lr_ext=s.lr_ext, batch=s.batch, seed=s.seed + 7, w_acc=s.w_acc, weighted=True)
print(f"{effect} j{j}: as is + a full weighted schedule: {est(m):.4f} ({time.time()-t0:.0f}s)", flush=True)
