//! The TCN context encoder (python/exolan/encoder.py, `TCNEncoder`) with a reverse pass: the training kernel
//! of the encoder, as `grad` is that of the Lagrangian's terms.
//!
//! Block i (dilation d = 2^i, kernel K): h₁ = relu(conv₁(x))·keep, h₂ = relu(conv₂(h₁)), y = relu(h₂ + res(x))·keep,
//! with res a 1×1 conv where the channel counts differ, else the identity, and every conv causal:
//! a[t] = b + Σ_k W[:, :, k] x[t − (K−1−k)·d], x = 0 before t = 0. The input is multiplied by keep first.
//! Activations are position-major (a sequence is a T × channels matrix), so a conv is one `gemm` per tap over
//! all of a sequence's positions, the tap's shift an offset of the output rows; the reverse pass is per tap
//! one product for the weight gradient and one for the input gradient. ReLU's derivative is read from the
//! saved outputs (torch's rule: 1 where the output is > 0), which also holds keep's zeros.
//!
//! The forward pass keeps a tape (`TcnTape`) rather than the reverse pass recomputing each sequence's blocks:
//! at a training batch (32 × 318, float32, one thread) recomputing cost 1.1 ms more than writing and reading it.
//!
//! Sequences go in chunks of whole sequences (about `CHUNK_POSITIONS` positions); chunks run on the pool's
//! threads, each sums its weight gradients apart and the chunks' sums are added in chunk order, so the result
//! is the same bit for bit at any thread count.

use std::any::Any;
use std::sync::Mutex;

use crate::error::{Error, Result};
use crate::pool::{Chunks, Pool};
use crate::real::Real;
use crate::simd::{simd_dispatch, Simd};
use kernels::{backward_chunk, forward_chunk};

mod kernels;

/// Positions per chunk (whole sequences, at least one): a training batch's 32 sequences of 318 give 32 chunks.
pub const CHUNK_POSITIONS: usize = 512;

/// One conv's weights as torch stores them: W (out × in × taps, row-major) and b (out).
pub type ConvRef<'a, T> = (&'a [T], &'a [T]);
/// Weight gradients in torch's layout, one (dW, db) per conv in the order the weights were given.
pub type ConvGrads<T> = Vec<(Vec<T>, Vec<T>)>;

fn padded<T: Real>(x: usize) -> usize {
    x.div_ceil(T::LANES) * T::LANES
}

/// A causal dilated conv, channel counts zero-padded to the lane count (`cip` in, `op` out).
struct Conv<T> {
    cin: usize,
    cip: usize,
    cout: usize,
    op: usize,
    taps: usize,
    dil: usize,
    /// Per tap Wₖᵀ (cin × op): the forward product's right operand.
    wt: Vec<T>,
    /// Per tap Wₖ (cout × cip): the input gradient's right operand.
    w: Vec<T>,
    b: Vec<T>,
}

impl<T: Real> Conv<T> {
    fn new(w: &[T], b: &[T], cout: usize, cin: usize, taps: usize, dil: usize) -> Conv<T> {
        let (cip, op) = (padded::<T>(cin), padded::<T>(cout));
        let z = T::default();
        let (mut wt, mut wp, mut bp) = (vec![z; taps * cin * op], vec![z; taps * cout * cip], vec![z; op]);
        bp[..cout].copy_from_slice(b);
        for o in 0..cout {
            for i in 0..cin {
                for k in 0..taps {
                    let v = w[(o * cin + i) * taps + k];
                    wt[(k * cin + i) * op + o] = v;
                    wp[(k * cout + o) * cip + i] = v;
                }
            }
        }
        Conv { cin, cip, cout, op, taps, dil, wt, w: wp, b: bp }
    }
    /// How far back tap k reads.
    fn shift(&self, k: usize) -> usize {
        (self.taps - 1 - k) * self.dil
    }
    /// This conv's share of a gradient buffer: dWₖ (cout × cip) per tap, then db (op).
    fn grad_len(&self) -> usize {
        self.taps * self.cout * self.cip + self.op
    }
}

struct Block<T> {
    conv1: Conv<T>,
    conv2: Conv<T>,
    res: Option<Conv<T>>,
}

impl<T: Real> Block<T> {
    /// conv1's, conv2's and res's shares of a gradient buffer, in that order.
    fn grad_len(&self) -> usize {
        self.conv1.grad_len() + self.conv2.grad_len() + self.res.as_ref().map_or(0, Conv::grad_len)
    }
}

/// The prepared weights of a TCN encoder.
pub struct Tcn<T> {
    c_in: usize,
    cip: usize,
    hidden: usize,
    hp: usize,
    blocks: Vec<Block<T>>,
    simd: Simd,
}

/// What a forward pass keeps for the reverse one: per sequence the input (times keep) and every block's h₁ and
/// y; every block's ReLU mask of h₂ (its values are needed nowhere else: a quarter less memory traffic); keep.
pub struct TcnTape<T: Send + 'static> {
    batch: usize,
    t_len: usize,
    data: Vec<T>,
    masks: Vec<u8>,
    keep: Vec<T>,
}

impl<T: TcnReal> Tcn<T> {
    /// Prepare an encoder of `levels` blocks (dilations 1, 2, 4, …) from its convs in module order: per block
    /// conv1, conv2, then res where the block's input has other than `hidden` channels (block 0 with c_in ≠ hidden).
    pub fn new(c_in: usize, hidden: usize, levels: usize, kernel: usize, convs: &[ConvRef<T>]) -> Result<Tcn<T>> {
        if c_in == 0 || hidden == 0 || levels == 0 || kernel == 0 {
            return Err(Error::InputShape(format!("tcn: c_in {c_in}, hidden {hidden}, levels {levels}, kernel {kernel} must be > 0")));
        }
        let want = 2 * levels + usize::from(c_in != hidden);
        if convs.len() != want {
            return Err(Error::InputShape(format!("tcn: {} convs given, expected {want}", convs.len())));
        }
        let mut it = convs.iter().enumerate();
        let mut conv = |cin: usize, taps: usize, dil: usize| -> Result<Conv<T>> {
            let (i, &(w, b)) = it.next().expect("counted above");
            if w.len() != hidden * cin * taps || b.len() != hidden {
                return Err(Error::InputShape(format!(
                    "tcn: conv {i} has {} weights and {} biases, expected {hidden} x {cin} x {taps} and {hidden}", w.len(), b.len())));
            }
            Ok(Conv::new(w, b, hidden, cin, taps, dil))
        };
        let mut blocks = Vec::with_capacity(levels);
        for l in 0..levels {
            let (cin, dil) = (if l == 0 { c_in } else { hidden }, 1 << l);
            let conv1 = conv(cin, kernel, dil)?;
            let conv2 = conv(hidden, kernel, dil)?;
            let res = if cin != hidden { Some(conv(cin, 1, 1)?) } else { None };
            blocks.push(Block { conv1, conv2, res });
        }
        Ok(Tcn { c_in, cip: padded::<T>(c_in), hidden, hp: padded::<T>(hidden), blocks, simd: crate::simd::detect() })
    }

    /// (out, in, taps) of every conv, in the order `new` takes them.
    pub fn shapes(&self) -> Vec<(usize, usize, usize)> {
        self.convs().map(|c| (c.cout, c.cin, c.taps)).collect()
    }

    /// z (batch × t_len × hidden) from x (batch × t_len × c_in) and keep (batch × t_len, 0 before a trial's
    /// start, else 1); with `tape`, what the reverse pass needs is kept there.
    #[allow(clippy::too_many_arguments)]
    pub fn forward(&self, x: &[T], keep: &[T], batch: usize, t_len: usize, z: &mut [T], tape: Option<&mut TcnTape<T>>,
                   pool: &Pool) -> Result<()> {
        if x.len() != batch * t_len * self.c_in || keep.len() != batch * t_len || z.len() != batch * t_len * self.hidden {
            return Err(Error::InputShape(format!(
                "tcn forward: x has {} values, keep {}, z {}, for {batch} sequences of {t_len} with {} channels in and {} out",
                x.len(), keep.len(), z.len(), self.c_in, self.hidden)));
        }
        let (sl, ml, spc) = (self.seq_len(t_len), self.mask_len(t_len), seqs_per_chunk(t_len));
        let (mut none, mut no_masks) = (Vec::new(), Vec::new());
        let (data, masks, kept): (&mut [T], &mut [u8], bool) = match tape {
            Some(tp) => {
                tp.batch = batch;
                tp.t_len = t_len;
                if tp.data.capacity() == 0 {
                    tp.data = reuse::<T>(batch * sl);
                    tp.masks = reuse::<u8>(batch * ml);
                }
                // every value is written by the forward pass before anything reads it: no need to clear
                tp.data.resize(batch * sl, T::default());
                tp.masks.resize(batch * ml, 0);
                tp.keep.clear();
                tp.keep.extend_from_slice(keep);
                (&mut tp.data, &mut tp.masks, true)
            }
            None => (&mut none, &mut no_masks, false),
        };
        let outs = (Chunks::new(data, spc * sl), Chunks::new(masks, spc * ml), Chunks::new(z, spc * t_len * self.hidden));
        let job = FwdJob { k: self, x, keep, batch, t_len, spc, tape: kept };
        pool.run(batch.div_ceil(spc), &|ci| {
            // SAFETY: each chunk index is taken by one task only.
            let (tp, tm, zo) = unsafe { (outs.0.get(ci), outs.1.get(ci), outs.2.get(ci)) };
            T::forward_chunk(self.simd, &job, ci, tp, tm, zo);
        });
        Ok(())
    }

    /// The reverse pass over a tape of `forward`: the gradient of z in, every conv's weight gradients out (in
    /// the order `new` takes them, torch's layout), and that of x written into `dx` where given.
    pub fn backward(&self, tape: &TcnTape<T>, gz: &[T], dx: Option<&mut [T]>, pool: &Pool) -> Result<ConvGrads<T>> {
        let (batch, t_len) = (tape.batch, tape.t_len);
        if tape.data.len() != batch * self.seq_len(t_len) || tape.masks.len() != batch * self.mask_len(t_len) {
            return Err(Error::InputShape("tcn backward: the tape was not written by this encoder's forward pass".into()));
        }
        if gz.len() != batch * t_len * self.hidden || dx.as_ref().is_some_and(|d| d.len() != batch * t_len * self.c_in) {
            return Err(Error::InputShape(format!("tcn backward: inconsistent lengths for {batch} sequences of {t_len}")));
        }
        let spc = seqs_per_chunk(t_len);
        let chunks = batch.div_ceil(spc);
        let gl = self.grad_len();
        let mut partial = vec![T::default(); chunks * gl];
        {
            let want_dx = dx.is_some();
            let mut none = Vec::new();
            let dx = dx.unwrap_or(&mut none);
            let outs = (Chunks::new(&mut partial, gl), Chunks::new(dx, spc * t_len * self.c_in));
            let job = BwdJob { k: self, tape, gz, spc, dx: want_dx };
            pool.run(chunks, &|ci| {
                // SAFETY: each chunk index is taken by one task only.
                let (pg, dxo) = unsafe { (outs.0.get(ci), outs.1.get(ci)) };
                T::backward_chunk(self.simd, &job, ci, pg, dxo);
            });
        }
        Ok(self.unpad(&crate::grad::sum_chunks(&partial, gl)))
    }
}

impl<T: Real> Tcn<T> {
    fn convs(&self) -> impl Iterator<Item = &Conv<T>> {
        self.blocks.iter().flat_map(|b| [Some(&b.conv1), Some(&b.conv2), b.res.as_ref()].into_iter().flatten())
    }

    fn grad_len(&self) -> usize {
        self.convs().map(Conv::grad_len).sum()
    }

    /// Values of one sequence's tape: the input (t × cip), then per block h₁ and y (t × hp each).
    fn seq_len(&self, t: usize) -> usize {
        t * self.cip + 2 * self.blocks.len() * t * self.hp
    }

    /// ReLU masks of one sequence's tape: per block h₂ > 0 (t × hp).
    fn mask_len(&self, t: usize) -> usize {
        self.blocks.len() * t * self.hp
    }

    /// A gradient buffer's padded blocks back in torch's layout (W out × in × taps).
    fn unpad(&self, g: &[T]) -> ConvGrads<T> {
        let mut off = 0;
        self.convs().map(|c| {
            let mut dw = vec![T::default(); c.cout * c.cin * c.taps];
            for k in 0..c.taps {
                for o in 0..c.cout {
                    for i in 0..c.cin {
                        dw[(o * c.cin + i) * c.taps + k] = g[off + (k * c.cout + o) * c.cip + i];
                    }
                }
            }
            let db = g[off + c.taps * c.cout * c.cip..][..c.cout].to_vec();
            off += c.grad_len();
            (dw, db)
        }).collect()
    }
}

fn seqs_per_chunk(t_len: usize) -> usize {
    (CHUNK_POSITIONS / t_len.max(1)).max(1)
}

impl<T: TcnReal> TcnTape<T> {
    pub fn new() -> TcnTape<T> {
        TcnTape { batch: 0, t_len: 0, data: Vec::new(), masks: Vec::new(), keep: Vec::new() }
    }
    pub fn batch(&self) -> usize {
        self.batch
    }
}

impl<T: TcnReal> Default for TcnTape<T> {
    fn default() -> Self {
        TcnTape::new()
    }
}

/// A tape's buffers (7.5 MB at a training batch) goes back to a small free list when the tape is dropped, so the
/// next step's forward pass neither clears it nor faults its pages in again. Apart from `grad`'s list, whose
/// first-fit pick would hand this small buffer the terms' large one.
impl<T: Send + 'static> Drop for TcnTape<T> {
    fn drop(&mut self) {
        recycle(std::mem::take(&mut self.data));
        recycle(std::mem::take(&mut self.masks));
    }
}

fn recycle<T: Send + 'static>(data: Vec<T>) {
    if data.capacity() > 0 {
        let mut list = FREE.lock().unwrap_or_else(|p| p.into_inner());
        list.push(Box::new(data));
        if list.len() > KEEP {
            list.remove(0);
        }
    }
}

/// Free tape buffers (at most `KEEP`, the newest kept: a tape's values and masks, twice).
const KEEP: usize = 4;
static FREE: Mutex<Vec<Box<dyn Any + Send>>> = Mutex::new(Vec::new());

/// A freed tape buffer of T with room for `len` values if there is one, else a new empty one.
fn reuse<T: 'static>(len: usize) -> Vec<T> {
    let mut list = FREE.lock().unwrap_or_else(|p| p.into_inner());
    let pos = list.iter().position(|b| b.downcast_ref::<Vec<T>>().is_some_and(|v| v.capacity() >= len));
    match pos {
        Some(i) => *list.remove(i).downcast::<Vec<T>>().expect("checked above"),
        None => Vec::new(),
    }
}

#[doc(hidden)]
pub struct FwdJob<'a, T> {
    k: &'a Tcn<T>,
    x: &'a [T],
    keep: &'a [T],
    batch: usize,
    t_len: usize,
    spc: usize,
    tape: bool,
}

#[doc(hidden)]
pub struct BwdJob<'a, T: Send + 'static> {
    k: &'a Tcn<T>,
    tape: &'a TcnTape<T>,
    gz: &'a [T],
    spc: usize,
    dx: bool,
}

/// The float types the encoder's kernel runs in, each with its SIMD dispatch.
pub trait TcnReal: Real {
    #[doc(hidden)]
    fn forward_chunk(simd: Simd, job: &FwdJob<Self>, ci: usize, tape: &mut [Self], masks: &mut [u8], z: &mut [Self]);
    #[doc(hidden)]
    fn backward_chunk(simd: Simd, job: &BwdJob<Self>, ci: usize, grad: &mut [Self], dx: &mut [Self]);
}

macro_rules! tcn_real {
    ($t:ty, $f:ident, $fd:ident, $b:ident, $bd:ident) => {
        #[inline(always)]
        fn $f<const FMA: bool, const WIDE: bool>(job: &FwdJob<$t>, ci: usize, tape: &mut [$t], masks: &mut [u8], z: &mut [$t]) {
            forward_chunk::<$t, FMA, WIDE>(job, ci, tape, masks, z)
        }
        simd_dispatch!(fn $fd(job: &FwdJob<$t>, ci: usize, tape: &mut [$t], masks: &mut [u8], z: &mut [$t]) = $f;);
        #[inline(always)]
        fn $b<const FMA: bool, const WIDE: bool>(job: &BwdJob<$t>, ci: usize, grad: &mut [$t], dx: &mut [$t]) {
            backward_chunk::<$t, FMA, WIDE>(job, ci, grad, dx)
        }
        simd_dispatch!(fn $bd(job: &BwdJob<$t>, ci: usize, grad: &mut [$t], dx: &mut [$t]) = $b;);
        impl TcnReal for $t {
            fn forward_chunk(simd: Simd, job: &FwdJob<$t>, ci: usize, tape: &mut [$t], masks: &mut [u8], z: &mut [$t]) {
                $fd(simd, job, ci, tape, masks, z)
            }
            fn backward_chunk(simd: Simd, job: &BwdJob<$t>, ci: usize, grad: &mut [$t], dx: &mut [$t]) {
                $bd(simd, job, ci, grad, dx)
            }
        }
    };
}
tcn_real!(f32, fwd32, fwd32_simd, bwd32, bwd32_simd);
tcn_real!(f64, fwd64, fwd64_simd, bwd64, bwd64_simd);

#[cfg(test)]
mod tests;
