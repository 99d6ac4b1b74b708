//! A tanh MLP carried with its q-tangents through a tile of samples, and its reverse pass.
//!
//! A tile's activations are one row-major matrix of `s · t` rows: rows 0..t the values of its t samples,
//! rows (1+k)·t.. their q_k-tangents. One product per layer then serves every stream (the bias enters the
//! value rows only), and the reverse pass is three products per layer: the weight gradient, the input
//! gradient, and the elementwise chain through tanh, whose tangent rows also depend on h:
//!
//!   h = tanh(a), ḣ_k = (1 − h²) ȧ_k   ⇒   ā = (1 − h²)(h̄ − 2h Σ_k ḣ̄_k ȧ_k),  ǡ_k = (1 − h²) ḣ̄_k.
//!
//! Widths are zero-padded to the lane count, which adds nothing: a padded unit has zero weights in and out.

use super::gemm::gemm;
use crate::real::Real;

/// A dense layer as torch stores it (W out × in, b), zero-padded: `w` (op × ip), `wt` = Wᵀ (ip × op).
pub(crate) struct Layer<T> {
    pub inp: usize,
    pub out: usize,
    pub ip: usize,
    pub op: usize,
    pub w: Vec<T>,
    pub wt: Vec<T>,
    pub b: Vec<T>,
}

pub(crate) fn padded<T: Real>(x: usize) -> usize {
    x.div_ceil(T::LANES) * T::LANES
}

impl<T: Real> Layer<T> {
    pub(crate) fn new(w: &[T], b: &[T], out: usize, inp: usize) -> Layer<T> {
        let (ip, op) = (padded::<T>(inp), padded::<T>(out));
        let z = T::default();
        let (mut wp, mut wt, mut bp) = (vec![z; op * ip], vec![z; ip * op], vec![z; op]);
        for o in 0..out {
            bp[o] = b[o];
            for i in 0..inp {
                wp[o * ip + i] = w[o * inp + i];
                wt[i * op + o] = w[o * inp + i];
            }
        }
        Layer { inp, out, ip, op, w: wp, wt, b: bp }
    }
    /// This layer's share of a gradient buffer: dW (op × ip), then db (op).
    pub(crate) fn grad_len(&self) -> usize {
        self.op * self.ip + self.op
    }
}

/// Hidden layers (tanh) and a linear output layer.
pub(crate) struct Net<T> {
    pub layers: Vec<Layer<T>>,
}

impl<T: Real> Net<T> {
    pub(crate) fn grad_len(&self) -> usize {
        self.layers.iter().map(Layer::grad_len).sum()
    }
    /// The tape of one tile of `rows` stream rows: every layer's output block.
    pub(crate) fn tape_len(&self, rows: usize) -> usize {
        rows * self.layers.iter().map(|l| l.op).sum::<usize>()
    }
    pub(crate) fn width(&self) -> usize {
        self.layers.iter().map(|l| l.op.max(l.ip)).max().unwrap_or(0)
    }
    /// Offset of the output layer's block in a tile's tape.
    pub(crate) fn out_offset(&self, rows: usize) -> usize {
        rows * self.layers[..self.layers.len() - 1].iter().map(|l| l.op).sum::<usize>()
    }
}

/// One tile's inputs: `t` samples, `s` streams (value and n tangents), x = [φ(q), z, 0…] (t × ip₀) and
/// ∂φ/∂q_k (t × n × 2) in joint k's columns `cols[k]` (the second is `usize::MAX` for a prismatic joint).
pub(crate) struct Tile<'a, T> {
    pub t: usize,
    pub s: usize,
    pub x: &'a [T],
    pub dphi: &'a [T],
    pub cols: &'a [(usize, usize)],
}

/// Forward pass of `net` over a tile, written straight into the tape: per hidden layer its output [h; ḣ] (which
/// is the next layer's input), then the output block [u; u̇].
#[inline(always)]
pub(crate) fn forward<T: Real, const FMA: bool, const WIDE: bool>(net: &Net<T>, tile: &Tile<T>, tape: &mut [T]) {
    let (t, s, n) = (tile.t, tile.s, tile.s - 1);
    let rows = s * t;
    let l0 = &net.layers[0];
    let op = l0.op;
    let (a, mut rest) = tape.split_at_mut(rows * op);
    for r in 0..t {
        a[r * op..(r + 1) * op].copy_from_slice(&l0.b);
    }
    gemm::<T, FMA, WIDE>(t, l0.ip, op, tile.x, l0.ip, 1, &l0.wt, op, a, op, true);
    for k in 0..n {
        let (ca, cb) = tile.cols[k];
        let wa = &l0.wt[ca * op..(ca + 1) * op];
        for r in 0..t {
            let (da, db) = (tile.dphi[(r * n + k) * 2], tile.dphi[(r * n + k) * 2 + 1]);
            let row = &mut a[((1 + k) * t + r) * op..((1 + k) * t + r + 1) * op];
            if cb == usize::MAX {
                for (y, w) in row.iter_mut().zip(wa) {
                    *y = *w * da;
                }
            } else {
                for ((y, w), v) in row.iter_mut().zip(wa).zip(&l0.wt[cb * op..(cb + 1) * op]) {
                    *y = T::madd::<FMA>(*v, db, *w * da);
                }
            }
        }
    }
    let mut a = a;
    for li in 1..net.layers.len() {
        let w = net.layers[li - 1].op;
        // [a; ȧ] -> [h; ḣ] in place: the tape's block and the next layer's input
        T::tanh_tangent::<FMA, WIDE>(&mut a[..rows * w], t * w, s);
        let next = &net.layers[li];
        let no = next.op;
        let (b, r2) = std::mem::take(&mut rest).split_at_mut(rows * no);
        for r in 0..rows {
            let dst = &mut b[r * no..(r + 1) * no];
            if r < t {
                dst.copy_from_slice(&next.b);
            } else {
                dst.fill(T::default());
            }
        }
        if next.out <= NARROW {
            for r in 0..rows {
                let x = &a[r * w..(r + 1) * w];
                for j in 0..next.out {
                    b[r * no + j] = b[r * no + j] + dot::<T, FMA>(x, &next.w[j * w..(j + 1) * w]);
                }
            }
        } else {
            gemm::<T, FMA, WIDE>(rows, w, no, a, w, 1, &next.wt, no, b, no, true);
        }
        a = b;
        rest = r2;
    }
}

/// Scratch of the reverse pass (s·t·width values each).
pub(crate) struct BackBufs<T> {
    pub g: Vec<T>,
    pub gb: Vec<T>,
    sb: Vec<T>,
}

impl<T: Real> BackBufs<T> {
    pub(crate) fn new(len: usize) -> BackBufs<T> {
        BackBufs { g: vec![T::default(); len], gb: vec![T::default(); len], sb: vec![T::default(); len] }
    }
}

/// Reverse pass of `net` over a tile whose forward pass left `tape`. `bufs.g` holds the gradient of the
/// output block (s·t × op_out, zero in padded columns); on return `grad` (this net's dW, db per layer)
/// has the tile's weight gradients added, `gx` (t × ip₀) the gradient of x and `gdphi` (t × n × 2) that
/// of ∂φ/∂q added.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward<T: Real, const FMA: bool, const WIDE: bool>(
    net: &Net<T>, tile: &Tile<T>, tape: &[T], bufs: &mut BackBufs<T>, grad: &mut [T], gx: &mut [T], gdphi: &mut [T],
) {
    let (t, s, n) = (tile.t, tile.s, tile.s - 1);
    let rows = s * t;
    let nl = net.layers.len();
    let mut toff = vec![0usize; nl];
    let mut goff = vec![0usize; nl];
    for l in 1..nl {
        toff[l] = toff[l - 1] + rows * net.layers[l - 1].op;
        goff[l] = goff[l - 1] + net.layers[l - 1].grad_len();
    }
    let BackBufs { g, gb, sb } = bufs;
    for li in (0..nl).rev() {
        let layer = &net.layers[li];
        let (ip, op) = (layer.ip, layer.op);
        let (dw, rest) = grad[goff[li]..].split_at_mut(op * ip);
        let db = &mut rest[..op];
        for r in 0..t {
            for (d, x) in db.iter_mut().zip(&g[r * op..(r + 1) * op]) {
                *d = *d + *x;
            }
        }
        if li == 0 {
            first_layer::<T, FMA, WIDE>(layer, tile, g, dw, gx, gdphi);
            return;
        }
        // the layer's input: the layer below's output [h; ḣ], as the forward pass left it
        let prev = &tape[toff[li - 1]..toff[li - 1] + rows * ip];
        if layer.out <= NARROW {
            narrow_back::<T, FMA>(layer, rows, g, prev, dw, gb);
        } else {
            gemm::<T, FMA, WIDE>(op, rows, ip, g, 1, op, prev, ip, dw, ip, true);
            gemm::<T, FMA, WIDE>(rows, op, ip, g, op, 1, &layer.w, ip, gb, ip, false);
        }
        tanh_back::<T, FMA>(prev, t, n, ip, gb, sb);
        std::mem::swap(g, gb);
    }
}

/// Layers with at most this many outputs (the networks' heads: L's n(n+1)/2 entries, V's one) run as dot
/// products and row updates instead of a product padded to the lane count.
const NARROW: usize = 6;

/// The reverse of a narrow layer: dW[j] += Σ_r ḡ[r][j] x[r] and x̄[r] = Σ_j ḡ[r][j] W[j] (x̄ overwritten).
#[inline(always)]
fn narrow_back<T: Real, const FMA: bool>(layer: &Layer<T>, rows: usize, g: &[T], xs: &[T], dw: &mut [T], gx: &mut [T]) {
    let (ip, op) = (layer.ip, layer.op);
    for r in 0..rows {
        let x = &xs[r * ip..(r + 1) * ip];
        let gr = &mut gx[r * ip..(r + 1) * ip];
        gr.fill(T::default());
        for j in 0..layer.out {
            let gj = g[r * op + j];
            for ((d, xx), (y, w)) in dw[j * ip..(j + 1) * ip].iter_mut().zip(x).zip(gr.iter_mut().zip(&layer.w[j * ip..(j + 1) * ip])) {
                *d = T::madd::<FMA>(gj, *xx, *d);
                *y = T::madd::<FMA>(gj, *w, *y);
            }
        }
    }
}

/// Through tanh and the tangents' factor: the gradient of a layer's output [h̄; ḣ̄_k] in `g` becomes that of its
/// pre-activations [ā; ǡ_k], from its output [h; ḣ_k] (ḣ_k = (1 − h²) ȧ_k, so ∂ḣ_k/∂a = −2h ḣ_k):
/// ā = (1 − h²) h̄ − 2h Σ_k ḣ̄_k ḣ_k and ǡ_k = (1 − h²) ḣ̄_k.
#[inline(always)]
fn tanh_back<T: Real, const FMA: bool>(blk: &[T], t: usize, n: usize, w: usize, g: &mut [T], sb: &mut [T]) {
    let (h, hd) = blk[..(1 + n) * t * w].split_at(t * w);
    let (gv, gt) = g[..(1 + n) * t * w].split_at_mut(t * w);
    let sb = &mut sb[..t * w];
    sb.fill(T::default());
    for (gk, dk) in gt.chunks_exact_mut(t * w).zip(hd.chunks_exact(t * w)) {
        for (((s, gg), d), hh) in sb.iter_mut().zip(gk.iter_mut()).zip(dk).zip(h) {
            *s = T::madd::<FMA>(*gg, *d, *s);
            *gg = *gg * T::madd::<FMA>(-*hh, *hh, T::of(1.0));
        }
    }
    for ((gg, hh), s) in gv.iter_mut().zip(h).zip(sb.iter()) {
        *gg = T::madd::<FMA>(-*hh, *hh, T::of(1.0)) * *gg - T::of(2.0) * *hh * *s;
    }
}

/// The first layer's reverse: dW₀ from the values (a product) and from the tangents (only φ's columns of
/// each joint, summed over the tile as contiguous rows first), x̄ = ā W₀, and ∂φ/∂q's gradient as dot
/// products with those columns.
#[inline(always)]
fn first_layer<T: Real, const FMA: bool, const WIDE: bool>(layer: &Layer<T>, tile: &Tile<T>, g: &[T], dw: &mut [T], gx: &mut [T], gdphi: &mut [T]) {
    let (t, n) = (tile.t, tile.s - 1);
    let (ip, op) = (layer.ip, layer.op);
    gemm::<T, FMA, WIDE>(op, t, ip, g, 1, op, tile.x, ip, dw, ip, true);
    let mut col = vec![T::default(); 2 * op];
    for k in 0..n {
        let (ca, cb) = tile.cols[k];
        col.fill(T::default());
        let (cola, colb) = col.split_at_mut(op);
        let wa = &layer.wt[ca * op..(ca + 1) * op];
        for r in 0..t {
            let gr = &g[((1 + k) * t + r) * op..((1 + k) * t + r + 1) * op];
            let i = (r * n + k) * 2;
            let (da, db) = (tile.dphi[i], tile.dphi[i + 1]);
            for (c, x) in cola.iter_mut().zip(gr) {
                *c = T::madd::<FMA>(*x, da, *c);
            }
            gdphi[i] = gdphi[i] + dot::<T, FMA>(gr, wa);
            if cb != usize::MAX {
                for (c, x) in colb.iter_mut().zip(gr) {
                    *c = T::madd::<FMA>(*x, db, *c);
                }
                gdphi[i + 1] = gdphi[i + 1] + dot::<T, FMA>(gr, &layer.wt[cb * op..(cb + 1) * op]);
            }
        }
        for o in 0..op {
            dw[o * ip + ca] = dw[o * ip + ca] + cola[o];
            if cb != usize::MAX {
                dw[o * ip + cb] = dw[o * ip + cb] + colb[o];
            }
        }
    }
    gemm::<T, FMA, WIDE>(t, op, ip, g, op, 1, &layer.w, ip, gx, ip, true);
}

/// Σ a_i b_i in 16 partial sums (vectorises; the lengths here are multiples of the lane count).
#[inline(always)]
pub(crate) fn dot<T: Real, const FMA: bool>(a: &[T], b: &[T]) -> T {
    let mut acc = [T::default(); 16];
    let m = a.len().min(b.len());
    for (ca, cb) in a[..m].chunks_exact(16).zip(b[..m].chunks_exact(16)) {
        for l in 0..16 {
            acc[l] = T::madd::<FMA>(ca[l], cb[l], acc[l]);
        }
    }
    let mut s = T::default();
    for i in m / 16 * 16..m {
        s = T::madd::<FMA>(a[i], b[i], s);
    }
    for l in 0..16 {
        s = s + acc[l];
    }
    s
}
