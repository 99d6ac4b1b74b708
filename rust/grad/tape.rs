//! What a forward pass keeps for its reverse pass, and a small free list of tape buffers.

use super::dispatch::KernelReal;

/// What a forward pass keeps for the reverse one.
pub struct Tape<T: KernelReal> {
    pub(crate) samples: usize,
    pub(crate) data: Vec<T>,
    pub(crate) qd: Vec<T>,
    pub(crate) q: Vec<T>,
}

impl<T: KernelReal> Tape<T> {
    pub fn new() -> Tape<T> {
        Tape { samples: 0, data: Vec::new(), qd: Vec::new(), q: Vec::new() }
    }
    pub fn samples(&self) -> usize {
        self.samples
    }

    /// The buffer of a forward pass over `samples` samples, `len` values long: a freed one where there is one.
    /// Every value is written by the forward pass before anything reads it, so it is not cleared.
    pub(crate) fn prepare(&mut self, samples: usize, len: usize) -> &mut [T] {
        self.samples = samples;
        if self.data.capacity() == 0 {
            self.data = reuse::<T>(len);
        }
        self.data.resize(len, T::default());
        self.data.truncate(len);
        &mut self.data
    }
}

impl<T: KernelReal> Default for Tape<T> {
    fn default() -> Self {
        Tape::new()
    }
}

/// A tape's buffer (tens of MB at a training batch) goes back to a small free list when the tape is dropped,
/// so the next step's forward pass neither clears it nor faults its pages in again.
impl<T: KernelReal> Drop for Tape<T> {
    fn drop(&mut self) {
        let data = std::mem::take(&mut self.data);
        if data.capacity() > 0 {
            recycle(data);
        }
    }
}

/// Free tape buffers per float type (at most `KEEP`, the largest kept).
const KEEP: usize = 4;

fn recycle<T: Send + 'static>(data: Vec<T>) {
    use std::any::Any;
    let mut list = free_list().lock().unwrap_or_else(|p| p.into_inner());
    list.push(Box::new(data) as Box<dyn Any + Send>);
    if list.len() > KEEP {
        list.remove(0);
    }
}

fn free_list() -> &'static std::sync::Mutex<Vec<Box<dyn std::any::Any + Send>>> {
    static FREE: std::sync::OnceLock<std::sync::Mutex<Vec<Box<dyn std::any::Any + Send>>>> = std::sync::OnceLock::new();
    FREE.get_or_init(|| std::sync::Mutex::new(Vec::new()))
}

/// A freed tape buffer of T with room for `len` values if there is one, else a new empty one.
fn reuse<T: 'static>(len: usize) -> Vec<T> {
    let mut list = free_list().lock().unwrap_or_else(|p| p.into_inner());
    let pos = list.iter().position(|b| b.downcast_ref::<Vec<T>>().is_some_and(|v| v.capacity() >= len));
    match pos {
        Some(i) => *list.remove(i).downcast::<Vec<T>>().expect("checked above"),
        None => Vec::new(),
    }
}
