"""Independent fits side by side: a few threads shared by the whole run, nested calls included.

Why threads: every fit runs torch at one intra-op thread with its own seeded minibatch generator, and torch
releases the GIL inside its kernels, so two fits on two threads keep two cores busy and give the same bits as
one after the other (measured: two fits from scratch of the 4-user world, 1.82x, identical weights;
docs/DIAGNOSIS.md, "Time"). Why not a `concurrent.futures` pool: a candidate's task asks for further fits (its
second look's seeds) from inside a worker, and a fixed pool whose workers wait on their own sub-tasks deadlocks.
Here the caller always works through its own list, and takes a free slot for a helper thread where one is
left, so the run never holds more than `n` threads busy and a nested call cannot wait on itself; a slot freed
later goes to a list whose work nobody has taken yet (one thread's nested list of four fits beside another's of
two would otherwise leave a core to the pieces of one fit once the shorter list is done). `Ahead`: one
fit started before it is known to be needed, on a permit of the same pool, cancelled at its next progress tick."""
from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Callable, Sequence


class Workers:
    """At most `n` threads fitting at once: `map` runs zero-argument callables and returns their results in order;
    `once` makes a keyed result once when several threads ask for it. A thread holds one of the `n` permits while
    it works and gives it back while it waits (for a result another thread is making, or for its helpers), so a
    waiting thread never keeps a core idle that a nested call could use."""

    def __init__(self, n: int = 1):
        self.n = max(int(n), 1)
        self._permits = threading.Semaphore(self.n)
        self._held = threading.local()
        self._guard = threading.Lock()
        self._locks: dict = {}
        self._ahead: list = []      # every `Ahead` started on this pool (`running` cancels them when the run ends)
        self._open: list = []       # the `recruit` of every map with work left, offered each freed permit
        self._wanting = 0           # threads taking their permit back after a wait: they come first

    def _holds(self) -> bool:
        return getattr(self._held, "permit", False)

    def _take(self) -> None:
        self._permits.acquire()
        self._held.permit = True

    def _give(self) -> None:
        self._held.permit = False
        self._permits.release()
        self._offer()

    def _offer(self) -> None:
        """A freed permit to a map's work that no thread has taken yet, unless a thread waits to take one back."""
        with self._guard:
            if self._wanting:
                return
            open_ = list(self._open)
        for recruit in open_:
            recruit()

    def wait(self, block: Callable) -> None:
        """Run `block()` (a wait) without holding a permit, then take one again."""
        held = self._holds()
        if held:
            self._give()
        try:
            block()
        finally:
            if held:
                with self._guard:
                    self._wanting += 1
                try:
                    self._take()
                finally:
                    with self._guard:
                        self._wanting -= 1
                self._offer()                # a permit skipped while this thread wanted one

    def map(self, fns: Sequence[Callable]) -> list:
        fns = list(fns)
        out, todo, failed = [None] * len(fns), list(range(len(fns))), []
        lock, helpers = threading.Lock(), []
        entered = not self._holds()          # a caller from outside takes a permit for the call
        if entered:
            self._take()

        def take():
            with lock:
                return None if (failed or not todo) else todo.pop(0)

        def drain():
            while (i := take()) is not None:
                recruit()
                try:
                    out[i] = fns[i]()
                except BaseException as exc:       # re-raised in the caller, the other results dropped
                    failed.append(exc)

        stop = getattr(_STOP, "event", None)     # the caller's work, if cancelled (`Ahead`), stops its helpers too

        def helper():       # runs on a permit `recruit` took for it
            self._held.permit, _STOP.event = True, stop
            try:
                drain()
            finally:
                _STOP.event = None
                self._give()

        def recruit():
            # a helper for work nobody has taken, while a permit is free (helpers busy on an item take no other);
            # started under the lock: another thread's offer may recruit it, and the owner joins what it sees listed
            with lock:
                if todo and not failed and self._permits.acquire(blocking=False):
                    t = threading.Thread(target=helper, daemon=True)
                    t.start()
                    helpers.append(t)

        with self._guard:
            self._open.append(recruit)
        try:
            drain()
            for t in list(helpers):
                self.wait(t.join)
        finally:
            with self._guard:
                self._open.remove(recruit)
            if entered:
                self._give()
        if failed:
            raise failed[0]
        return out

    @contextmanager
    def hold(self, key):
        """`with workers.hold(key):` the one (re-entrant) lock of `key`, for a result that several threads may build
        on; the permit is given back while another thread holds it."""
        with self._guard:
            lk = self._locks.setdefault(key, threading.RLock())
        if not lk.acquire(blocking=False):
            self.wait(lk.acquire)
        try:
            yield
        finally:
            lk.release()

    def once(self, store: dict, key, make: Callable):
        """store[key], made by `make()` by the first thread that asks; the others wait for it."""
        with self.hold((id(store), key)):
            if key not in store:
                store[key] = make()
            return store[key]


_RUNNING: list = [None]     # the pool of the diagnosis running in this process (`running`), None outside one


@contextmanager
def running(pool: Workers):
    """`with running(pool):` the pool that fits split their minibatch steps over (`fit.train`) and that every fit
    of the run is scheduled on; on leaving, every `Ahead` started on it is cancelled."""
    prev, _RUNNING[0] = _RUNNING[0], pool
    try:
        yield pool
    finally:
        _RUNNING[0] = prev
        for ahead in pool._ahead:    # work started ahead that nobody took (the run ended, or raised) stops
            ahead.cancel()


def current() -> Workers | None:
    """The running diagnosis' pool (`running`), None outside a run."""
    return _RUNNING[0]


class Cancelled(Exception):
    """Raised inside a fit whose result is no longer wanted (`Ahead.cancel`), at its next progress tick."""


_STOP = threading.local()


def stop_or_go() -> None:
    """Raise `Cancelled` where the work on this thread was cancelled (`Ahead`): every fit's progress tick and the
    selection's candidate lines ask."""
    ev = getattr(_STOP, "event", None)
    if ev is not None and ev.is_set():
        raise Cancelled("cancelled")


class Ahead:
    """`make()` on a thread of its own, started before the caller knows it will want the result, on one of the
    pool's permits (it waits for one, so the run still never holds more than `n` threads busy). `result()` waits
    for it (without holding a permit meanwhile); `cancel()` stops its fit at the next progress tick."""

    def __init__(self, workers: Workers, make: Callable):
        self._workers, self._stop, self._done = workers, threading.Event(), threading.Event()
        self._out, self._exc = None, None
        with workers._guard:
            workers._ahead.append(self)

        def work():
            workers._take()
            _STOP.event = self._stop
            try:
                if not self._stop.is_set():
                    self._out = make()
            except Cancelled:
                pass
            except BaseException as exc:        # re-raised by `result()`
                self._exc = exc
            finally:
                _STOP.event = None
                workers._give()
                self._done.set()

        threading.Thread(target=work, daemon=True).start()

    def cancel(self) -> None:
        self._stop.set()

    @property
    def cancelled(self) -> bool:
        return self._stop.is_set()

    def result(self):
        self._workers.wait(self._done.wait)
        if self._exc is not None:
            raise self._exc
        if self._stop.is_set() and self._out is None:
            raise Cancelled("the result was cancelled before it was made")
        return self._out
