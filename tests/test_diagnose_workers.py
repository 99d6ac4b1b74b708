"""The diagnosis' fits side by side (`diagnose.workers`): order, the thread bound, nesting, errors, the same
results as one at a time."""
import json
import threading
import time

import pytest

from exolan.diagnose import diagnose
from exolan.diagnose.synthetic import linear_drive
from exolan.diagnose.workers import Workers


class Busy:
    """Counts jobs running at once and the most seen (`peak`)."""
    def __init__(self):
        self.lock, self.now, self.peak = threading.Lock(), 0, 0

    def run(self, seconds: float) -> None:
        with self.lock:
            self.now += 1
            self.peak = max(self.peak, self.now)
        time.sleep(seconds)
        with self.lock:
            self.now -= 1


def test_map_keeps_the_order_and_never_runs_more_than_n_at_once():
    w, busy = Workers(2), Busy()

    def job(i):
        busy.run(0.02)
        return i * i

    # nested: each outer job maps inner jobs; a fixed pool waiting on its own sub-tasks would deadlock here
    out = w.map([lambda k=k: (job(k), w.map([lambda i=i: job(10 * k + i) for i in range(3)])) for k in range(4)])
    assert out == [(k * k, [(10 * k + i) ** 2 for i in range(3)]) for k in range(4)]
    assert busy.peak == 2
    assert Workers(1).map([lambda i=i: i for i in range(5)]) == list(range(5))


def test_a_permit_freed_by_a_shorter_list_goes_to_a_longer_lists_work():
    """Two jobs each map a nested list (one fit, then three): once the short list is done its thread waits and its
    permit goes to the long list's work nobody has taken, so that list runs on two threads, not one after the
    other on the thread that took it (a paired look's two base fits beside its four fits with the terms)."""
    w, busy, threads = Workers(2), Busy(), {}

    def job(name):
        threads[name] = threading.get_ident()
        busy.run(0.2)
        return name
    out = w.map([lambda: w.map([lambda: job("short")]),
                 lambda: w.map([lambda i=i: job(f"long{i}") for i in range(3)])])
    assert out == [["short"], ["long0", "long1", "long2"]]
    assert len({threads[f"long{i}"] for i in range(3)}) > 1
    assert busy.peak == 2


def test_a_helper_recruited_by_another_threads_offer_is_started_before_its_list_is_joined(monkeypatch):
    """A permit given back on one thread recruits a helper for a map another thread owns; where that helper's
    thread is slow to start, the owner may run out of work first and join its helpers: it must never meet one not
    yet started (seen once in a test run beside a CPU hog: "cannot join thread before it is started")."""
    from exolan.diagnose import workers as W

    class SlowStart(threading.Thread):
        def start(self):
            time.sleep(0.2)             # the recruiting thread preempted between listing and starting it
            super().start()
    monkeypatch.setattr(W.threading, "Thread", SlowStart)
    w = Workers(2)
    # main: 0.05 s, then waits for its helper, whose nested map holds 0.1 s and a tiny item; the permit main gives
    # back recruits a (slow) helper for the tiny item while the nested map's owner is still busy
    out = w.map([lambda: time.sleep(0.05) or "a", lambda: w.map([lambda: time.sleep(0.1) or "b", lambda: "c"])])
    assert out == ["a", ["b", "c"]]


def test_an_error_in_one_job_reaches_the_caller():
    def boom():
        raise ValueError("bad fit")
    with pytest.raises(ValueError, match="bad fit"):
        Workers(2).map([lambda: time.sleep(0.01), boom, lambda: 1])


def test_once_makes_a_result_once_when_two_threads_ask_at_once():
    w, store, made = Workers(2), {}, []

    def make():
        made.append(1)
        time.sleep(0.05)
        return "fit"
    assert w.map([lambda: w.once(store, "k", make)] * 2) == ["fit", "fit"]
    assert len(made) == 1


def _report(tmp_path, workers):
    trials, _ = linear_drive(n_trials=3, seconds=8.0, seed=5, viscous=8.0, coulomb=4.0)
    rep = diagnose(trials, out=tmp_path / str(workers), quick=True, hidden=8, steps_base=150, steps_refit=60,
                   physics_first=False, effects=("viscous_damping", "coulomb_friction"), verbose=False,
                   workers=workers)
    return json.loads(json.dumps({k: rep[k] for k in ("findings", "rejected", "extended")}, default=str))


def _without_timings(x):
    if isinstance(x, dict):
        return {k: _without_timings(v) for k, v in x.items() if not k.endswith("seconds")}
    if isinstance(x, list):
        return [_without_timings(v) for v in x]
    return x


def test_fits_side_by_side_give_the_same_diagnosis_as_one_at_a_time(tmp_path):
    one, two = _report(tmp_path, 1), _report(tmp_path, 2)
    assert _without_timings(one) == _without_timings(two)
    assert one["findings"] or one["rejected"]


def test_a_fit_in_pieces_takes_a_free_permit_with_the_same_bits():
    """`fit.train(pieces=2)` cuts every minibatch in two: on a pool with a permit free the second piece runs on
    another thread (a fit alone takes both cores), and the fitted weights are the bits of the pieces one after the
    other; the gradient is the whole minibatch's (the same fit in one piece ends within rounding of it)."""
    import copy
    import torch
    from exolan.diagnose import fit
    from exolan.diagnose.base import make_base
    from exolan.diagnose.flat import prepare
    trials, _ = linear_drive(n_trials=2, seconds=4.0, seed=3, viscous=8.0, coulomb=4.0)
    flat = prepare(trials, max_delay=0.05, seed=0)
    start = make_base(flat, hidden=8, z_dim=2, seed=0)
    threads, forward = set(), fit._forward_inertia

    def seen(*a, **k):
        threads.add(threading.get_ident())
        return forward(*a, **k)
    models = []
    for pool in (None, Workers(2)):
        m = copy.deepcopy(start)
        threads.clear()
        fit._forward_inertia = seen
        try:
            hist = fit.train(m, flat, 20, batch=256, seed=1, average=True, pieces=2, pool=pool)
        finally:
            fit._forward_inertia = forward
        models.append((m, hist, len(threads)))
    (m1, h1, t1), (m2, h2, t2) = models
    assert t1 == 1 and t2 > 1           # helpers are threads of each step's own
    assert h1 == h2
    assert all(torch.equal(a, b) for a, b in zip(m1.state_dict().values(), m2.state_dict().values()))
    whole = copy.deepcopy(start)
    h0 = fit.train(whole, flat, 20, batch=256, seed=1, average=True)
    assert h0[0] == pytest.approx(h1[0], rel=1e-5)          # the same first minibatch, the same loss
    assert all(torch.allclose(a, b, rtol=1e-3, atol=1e-4) for a, b in zip(whole.state_dict().values(),
                                                                       m1.state_dict().values()))


def test_a_thread_waiting_for_a_result_lends_its_permit_to_the_thread_making_it():
    """Two jobs need the same result: one makes it with a nested map of two parts, the other waits. The waiting
    thread's permit goes to the maker's nested map, so its two parts run side by side (not one after the other)."""
    class Observed(Workers):
        waiting = threading.Event()

        def wait(self, block):
            def blocked():
                self.waiting.set()          # the permit is given back by now
                block()
            super().wait(blocked)

    w, store, busy = Observed(2), {}, Busy()

    def make():
        assert w.waiting.wait(30)           # the other job arrives and waits
        w.map([lambda: busy.run(0.1)] * 2)
        return 1
    assert w.map([lambda: w.once(store, "k", make)] * 2) == [1, 1]
    assert busy.peak == 2


def test_a_result_made_ahead_holds_a_permit_and_is_handed_over():
    """`Ahead` works on one of the pool's permits (the run never holds more than n threads busy) and `result()`
    waits for it without holding one."""
    from exolan.diagnose.workers import Ahead
    w, busy = Workers(2), Busy()
    ahead = Ahead(w, lambda: (busy.run(0.2), "model")[1])
    time.sleep(0.05)
    w.map([lambda: busy.run(0.05)] * 3)
    assert ahead.result() == "model"
    assert busy.peak == 2


def test_a_fit_started_ahead_stops_at_its_next_progress_tick_when_cancelled():
    """A fit whose result is no longer wanted gives its core back at once: the progress callback of every fit
    (`settings.heartbeat`) raises `Cancelled` on its thread, and the permit returns to the pool."""
    from exolan.diagnose.settings import Settings, heartbeat
    from exolan.diagnose.workers import Ahead, Cancelled
    w, steps = Workers(1), []

    def fit():
        tick = heartbeat(Settings(verbose=False), "a fit", 10 ** 6)
        for i in range(10 ** 6):
            steps.append(i)
            tick(i, 0.0)
            time.sleep(0.001)
        return "finished"
    ahead = Ahead(w, fit)
    time.sleep(0.1)
    ahead.cancel()
    t0 = time.time()
    with pytest.raises(Cancelled):
        ahead.result()
    assert time.time() - t0 < 5 and 0 < len(steps) < 10 ** 6
    assert w.map([lambda: 1]) == [1]            # the only permit is back
    tick = heartbeat(Settings(verbose=False), "a fit on this thread", 10)
    tick(0, 0.0)                                # a fit on another thread is not cancelled with it


def test_the_helpers_of_work_started_ahead_stop_with_it():
    """Work started ahead may spread over free permits (`Workers.map` inside it: physics first's candidates side by
    side); cancelled, its helpers stop at their next tick too, not only its own thread, and every permit returns."""
    from exolan.diagnose.workers import Ahead, Cancelled, stop_or_go
    w, ticks = Workers(2), {}

    def job(k):
        for i in range(10 ** 5):
            ticks[k] = i
            stop_or_go()
            time.sleep(0.001)
        return k
    ahead = Ahead(w, lambda: w.map([lambda k=k: job(k) for k in range(2)]))
    time.sleep(0.2)
    ahead.cancel()
    t0 = time.time()
    with pytest.raises(Cancelled):
        ahead.result()
    assert time.time() - t0 < 5 and set(ticks) == {0, 1} and max(ticks.values()) < 10 ** 5 - 1
    assert w.map([lambda: 1, lambda: 2]) == [1, 2]      # both permits are back


def test_work_started_ahead_and_not_taken_stops_when_the_run_ends_even_on_an_error():
    """Every `Ahead` started on a run's pool is cancelled when the run leaves `workers.running`, also where the
    run raised before anyone took its result: no fit keeps a core busy after its diagnosis."""
    from exolan.diagnose.settings import Settings, heartbeat
    from exolan.diagnose.workers import Ahead, Cancelled, running
    w, steps = Workers(2), []

    def fit():
        tick = heartbeat(Settings(verbose=False), "a fit", 10 ** 6)
        for i in range(10 ** 6):
            steps.append(i)
            tick(i, 0.0)
            time.sleep(0.001)
        return "finished"
    with pytest.raises(RuntimeError):
        with running(w):
            ahead = Ahead(w, fit)
            time.sleep(0.1)
            raise RuntimeError("the run failed")
    time.sleep(0.5)                             # a tick is 1 ms: a fit still running would be ~500 steps on
    stopped = len(steps)
    time.sleep(0.3)
    assert 0 < stopped == len(steps)
    with pytest.raises(Cancelled):
        ahead.result()
    assert w.map([lambda: 1, lambda: 2]) == [1, 2]


def test_physics_first_with_its_extended_model_started_ahead_gives_the_same_diagnosis(tmp_path, capsys):
    """With a second worker, physics first's extended model is fitted beside the base fit (`physics_path.
    extended_ahead`) and handed over where the final terms are those it was started for: the diagnosis is the one
    made one fit at a time."""
    from exolan.diagnose.synthetic import servo_trial
    trials = [servo_trial(f"r{k}", seconds=8.0, seed=k, viscous=200.0, coulomb=20.0, offset=-3.0) for k in range(2)]

    def report(workers, verbose):
        rep = diagnose(trials, out=tmp_path / f"p{workers}", quick=True, hidden=8, steps_base=150, steps_refit=60,
                       effects=("viscous_damping", "coulomb_friction"), verbose=verbose, workers=workers)
        return json.loads(json.dumps({k: rep[k] for k in ("findings", "rejected", "extended", "physics")},
                                     default=str))
    one, two = report(1, False), report(2, True)
    assert "extended model started ahead" in capsys.readouterr().out
    assert [f["effect"] for f in two["findings"]] == ["viscous_damping", "coulomb_friction"]
    assert "without the terms" in two["extended"]["model"]
    assert _without_timings(one) == _without_timings(two)


def test_the_refit_noise_with_its_first_twin_made_ahead_is_the_one_made_in_place():
    """`procedure.reference` starts twin 0 of the refit noise beside the reference's refit (`workers.Ahead`);
    `refit_noise` takes it from there and fits the others: the same σ_r and twin differences, bit for bit, as
    every twin fitted in place, at one worker and at two."""
    import copy
    import numpy as np
    from exolan.diagnose import fit, procedure
    from exolan.diagnose.base import make_base
    from exolan.diagnose.flat import prepare
    from exolan.diagnose.settings import Settings
    from exolan.diagnose.workers import Ahead
    trials, _ = linear_drive(n_trials=2, seconds=4.0, seed=3, viscous=8.0, coulomb=4.0)
    flat = prepare(trials, max_delay=0.05, seed=0)
    base = make_base(flat, hidden=8, z_dim=2, seed=0)
    s = Settings(steps_refit=30, batch=256, verbose=False)
    held = flat.index("held")
    ref = copy.deepcopy(base)
    procedure.refit(ref, flat, s)

    def errors(m):
        e = fit.sq_errors(m, flat, held).sum(1)
        return e, e
    e_ref = errors(ref)[1]
    plain = procedure.refit_noise(base, flat, s, e_ref, errors, 3, "unweighted", Workers(1))
    for n in (1, 2):
        pool = Workers(n)
        first = Ahead(pool, lambda: procedure.twin_refit(base, flat, s, 0))
        ahead = procedure.refit_noise(base, flat, s, e_ref, errors, 3, "unweighted", pool, first=first)
        assert ahead["twin_differences"] == plain["twin_differences"] and ahead["sigma"] == plain["sigma"]
        assert all(np.array_equal(a, b) for a, b in zip(ahead["twin_d"], plain["twin_d"]))
    assert plain["sigma"] > 0


def test_the_extended_model_is_fitted_from_scratch_beside_the_forward_selection(tmp_path):
    """Step 7's fit from scratch of the accepted terms starts as soon as forward selection has accepted them, on a
    free permit (`selection._extended_ahead`), and step 7 takes it from the fits' cache: with two workers it is made
    during the selection, once, and the diagnosis is the one made one fit at a time."""
    from exolan.diagnose import refits, settings
    from exolan.diagnose.session import Tools
    trials, _ = linear_drive(n_trials=3, seconds=8.0, seed=5, viscous=8.0, coulomb=0.0)

    def report(workers):
        made = []

        def fresh(flat, s, effects, init, start, confused=None, trainer=refits.train):
            made.append((tuple(effects), settings._STEP[0]))
            return refits.fresh_fit(flat, s, effects, init, start, confused=confused, trainer=trainer)
        rep = diagnose(trials, out=tmp_path / str(workers), quick=True, hidden=8, steps_base=150, steps_refit=60,
                       physics_first=False, effects=("viscous_damping", "coulomb_friction"), verbose=False,
                       workers=workers, tools=Tools(fresh_fit=fresh))
        return json.loads(json.dumps({k: rep[k] for k in ("findings", "rejected", "extended")}, default=str)), made
    (one, made1), (two, made2) = report(1), report(2)
    assert [f["effect"] for f in one["findings"]] == ["viscous_damping"]
    ext = (("viscous_damping", 0),)
    assert [step for key, step in made2 if key == ext] == ["5/7 forward selection"]
    assert [key for key, _ in made1].count(ext) == 1
    assert _without_timings(one) == _without_timings(two)


def test_step_7s_comparison_base_is_started_ahead_beside_the_terms_fit():
    """`selection._extended_ahead` starts, beside the accepted terms' fit from scratch, what step 7's from-scratch
    look judges it against (`FitCache.optima`: the term-free base with the terms' recipe and its optimum twins),
    both on permits of the pool, side by side, the fit first, and keeps the latter on the session for step 7 to
    cancel."""
    from types import SimpleNamespace
    from exolan.diagnose import selection
    busy = Busy()

    class Cache:
        def fresh(self, key, init):
            busy.run(0.2)
            return ("fresh", key)

        def optima(self, key):
            busy.run(0.2)
            return ("optima", key)
    ss = SimpleNamespace(workers=Workers(2), cache=Cache(), optima_ahead=None)
    sel = SimpleNamespace(accepted=[("viscous_damping", 0)], acc_init={})
    key, fresh = selection._extended_ahead(ss, sel)
    assert fresh.result() == ("fresh", key) and ss.optima_ahead.result() == ("optima", key)
    assert busy.peak == 2
