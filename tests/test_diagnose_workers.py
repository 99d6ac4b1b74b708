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


def test_a_thread_waiting_for_a_result_lends_its_permit_to_the_thread_making_it():
    """Two jobs need the same result: one makes it with a nested map of two parts, the other waits. The waiting
    thread's permit goes to the maker's nested map, so its two parts run side by side (not one after the other)."""
    class Observed(Workers):
        waiting = threading.Event()

        def _wait(self, block):
            def blocked():
                self.waiting.set()          # the permit is given back by now
                block()
            super()._wait(blocked)

    w, store, busy = Observed(2), {}, Busy()

    def make():
        assert w.waiting.wait(30)           # the other job arrives and waits
        w.map([lambda: busy.run(0.1)] * 2)
        return 1
    assert w.map([lambda: w.once(store, "k", make)] * 2) == [1, 1]
    assert busy.peak == 2
