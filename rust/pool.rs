//! A fixed thread pool that never allocates after it is built.
//!
//! rayon's pool allocates under contention: a worker that first looks for work late pins crossbeam's
//! epoch for the first time and registers with its collector (a 2304-byte `Local`), and its global
//! injector allocates a new block every 63 jobs injected from outside the pool. A controller that runs
//! batched rollouts needs no allocation on every call, so batches run here instead: `threads − 1`
//! workers started at `Pool::new`, a batch is `tasks` indices handed out by an atomic counter (no
//! queue), and workers sleep on a `Mutex`/`Condvar` pair (futex-based on Linux: no allocation).

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;

use crate::error::{Error, Result};

/// The job of the current batch: a borrowed closure, type-erased. Only dereferenced between its
/// publication and the end of `Pool::run`, which waits until no worker holds it.
#[derive(Clone, Copy)]
struct Job(*const (dyn Fn(usize) + Sync));

// SAFETY: the closure behind the pointer is `Sync`, and `run` keeps it alive while workers use it.
unsafe impl Send for Job {}

struct State {
    generation: u64,
    job: Option<Job>,
    tasks: usize,
    /// Workers currently inside the job.
    active: usize,
    shutdown: bool,
}

struct Shared {
    state: Mutex<State>,
    start: Condvar,
    done: Condvar,
    next: AtomicUsize,
    panicked: AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Claim task indices until none are left.
fn drain(shared: &Shared, f: &(dyn Fn(usize) + Sync), tasks: usize) {
    loop {
        let i = shared.next.fetch_add(1, Ordering::Relaxed);
        if i >= tasks {
            return;
        }
        f(i);
    }
}

fn worker(shared: Arc<Shared>) {
    let mut seen = 0u64;
    loop {
        let (job, tasks) = {
            let mut st = shared.lock();
            loop {
                if st.shutdown {
                    return;
                }
                if st.generation != seen {
                    seen = st.generation;
                    if let Some(job) = st.job {
                        st.active += 1;
                        break (job, st.tasks);
                    }
                }
                st = shared.start.wait(st).unwrap_or_else(|p| p.into_inner());
            }
        };
        // SAFETY: `run` does not return (the closure stays alive) until `active` is back to 0.
        let f = unsafe { &*job.0 };
        if catch_unwind(AssertUnwindSafe(|| drain(&shared, f, tasks))).is_err() {
            shared.panicked.store(true, Ordering::SeqCst);
        }
        let mut st = shared.lock();
        st.active -= 1;
        if st.active == 0 {
            shared.done.notify_all();
        }
    }
}

/// `threads` ways of parallelism: the calling thread plus `threads − 1` workers.
pub struct Pool {
    shared: Arc<Shared>,
    workers: Vec<JoinHandle<()>>,
    /// One batch at a time (`run` from several threads at once queues here).
    batch: Mutex<()>,
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Pool {{ threads: {} }}", self.threads())
    }
}

impl Pool {
    /// Start `threads − 1` workers (allocates; do it once). `threads` 0 is taken as 1.
    pub fn new(threads: usize) -> Result<Pool> {
        Pool::with_start_handler(threads, |_| {})
    }

    /// As `new`; each worker first runs `start(index)`, index 1.. (e.g. to pin it to a core or
    /// raise its priority; the calling thread is index 0 and is the caller's to set up).
    pub fn with_start_handler(threads: usize, start: impl Fn(usize) + Send + Sync + 'static) -> Result<Pool> {
        let start = Arc::new(start);
        let shared = Arc::new(Shared {
            state: Mutex::new(State { generation: 0, job: None, tasks: 0, active: 0, shutdown: false }),
            start: Condvar::new(),
            done: Condvar::new(),
            next: AtomicUsize::new(0),
            panicked: AtomicBool::new(false),
        });
        let mut workers = Vec::with_capacity(threads.saturating_sub(1));
        for i in 1..threads.max(1) {
            let (s, st) = (shared.clone(), start.clone());
            let h = std::thread::Builder::new()
                .name(format!("exolan-pool-{i}"))
                .spawn(move || {
                    st(i);
                    worker(s)
                })
                .map_err(|e| Error::Io(format!("cannot start pool thread: {e}")))?;
            workers.push(h);
        }
        Ok(Pool { shared, workers, batch: Mutex::new(()) })
    }

    pub fn threads(&self) -> usize {
        self.workers.len() + 1
    }

    /// Call `f(i)` once for every i in 0..tasks, spread over the pool's threads and the caller's;
    /// returns when all calls have returned. Allocation-free. A panic in `f` is re-raised here.
    pub fn run(&self, tasks: usize, f: &(dyn Fn(usize) + Sync)) {
        if tasks == 0 {
            return;
        }
        if self.workers.is_empty() || tasks == 1 {
            (0..tasks).for_each(f);
            return;
        }
        let _one = self.batch.lock().unwrap_or_else(|p| p.into_inner());
        // SAFETY (lifetime erasure): the job is withdrawn and every worker out of it before we return.
        let job = Job(unsafe {
            std::mem::transmute::<*const (dyn Fn(usize) + Sync + '_), *const (dyn Fn(usize) + Sync + 'static)>(f)
        });
        {
            let mut st = self.shared.lock();
            self.shared.next.store(0, Ordering::Relaxed);
            st.job = Some(job);
            st.tasks = tasks;
            st.generation = st.generation.wrapping_add(1);
        }
        self.shared.start.notify_all();
        let mine = catch_unwind(AssertUnwindSafe(|| drain(&self.shared, f, tasks)));
        {
            let mut st = self.shared.lock();
            st.job = None;
            while st.active > 0 {
                st = self.shared.done.wait(st).unwrap_or_else(|p| p.into_inner());
            }
        }
        let theirs = self.shared.panicked.swap(false, Ordering::SeqCst);
        if let Err(p) = mine {
            std::panic::resume_unwind(p);
        }
        if theirs {
            panic!("a task panicked on an exolan pool thread");
        }
    }
}

impl Drop for Pool {
    fn drop(&mut self) {
        self.shared.lock().shutdown = true;
        self.shared.start.notify_all();
        for h in self.workers.drain(..) {
            let _ = h.join();
        }
    }
}

/// A process-wide pool of `threads` threads (0: one per core), started on first use and kept.
pub fn shared(threads: usize) -> Result<Arc<Pool>> {
    use std::collections::HashMap;
    use std::sync::OnceLock;
    static POOLS: OnceLock<Mutex<HashMap<usize, Arc<Pool>>>> = OnceLock::new();
    let t = if threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { threads };
    let mut pools = POOLS.get_or_init(|| Mutex::new(HashMap::new())).lock().unwrap_or_else(|p| p.into_inner());
    if let Some(p) = pools.get(&t) {
        return Ok(p.clone());
    }
    let p = Arc::new(Pool::new(t)?);
    pools.insert(t, p.clone());
    Ok(p)
}

/// Disjoint mutable chunks of one slice, handed to parallel tasks by index.
pub(crate) struct Chunks<'a, T> {
    ptr: *mut T,
    len: usize,
    chunk: usize,
    _life: std::marker::PhantomData<&'a mut [T]>,
}

// SAFETY: tasks take pairwise disjoint chunks (each index once, see `get`).
unsafe impl<T: Send> Sync for Chunks<'_, T> {}

impl<'a, T> Chunks<'a, T> {
    pub(crate) fn new(s: &'a mut [T], chunk: usize) -> Self {
        Chunks { ptr: s.as_mut_ptr(), len: s.len(), chunk, _life: std::marker::PhantomData }
    }
    /// Chunk `i` (the last one may be short).
    ///
    /// # Safety
    /// Each index may be taken by one task only, and not while another reference to it lives.
    #[allow(clippy::mut_from_ref)]
    pub(crate) unsafe fn get(&self, i: usize) -> &'a mut [T] {
        let start = (i * self.chunk).min(self.len);
        let end = (start + self.chunk).min(self.len);
        unsafe { std::slice::from_raw_parts_mut(self.ptr.add(start), end - start) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_task_once() {
        for threads in 1..=4 {
            let pool = Pool::new(threads).unwrap();
            for tasks in [0, 1, 2, 7, 100] {
                let hits: Vec<AtomicUsize> = (0..tasks).map(|_| AtomicUsize::new(0)).collect();
                for _ in 0..20 {
                    pool.run(tasks, &|i| {
                        hits[i].fetch_add(1, Ordering::Relaxed);
                    });
                }
                assert!(hits.iter().all(|h| h.load(Ordering::Relaxed) == 20), "threads {threads} tasks {tasks}");
            }
        }
    }

    #[test]
    fn panic_is_raised_and_pool_survives() {
        let pool = Pool::new(2).unwrap();
        let r = catch_unwind(AssertUnwindSafe(|| pool.run(8, &|i| assert!(i != 5))));
        assert!(r.is_err());
        let n = AtomicUsize::new(0);
        pool.run(8, &|_| {
            n.fetch_add(1, Ordering::Relaxed);
        });
        assert_eq!(n.load(Ordering::Relaxed), 8);
    }
}
