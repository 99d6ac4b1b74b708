//! The potential network's g = ∂V/∂q by reverse mode, and that pass's own reverse (the training gradient).
//!
//! V has one output, so its q-gradient costs one pass down the network (a product per hidden layer with W)
//! instead of the n tangent streams carried forward that the inertia network needs (`net.rs`); the training
//! step's reverse pass then adds two products per layer for the value path and two for the gradient path:
//! per hidden 64 x 64 layer six products against nine with n = 2 tangents.
//!
//! Per hidden layer i (value h_i = tanh(a_i), a_i = W_{i-1} h_{i-1} + b_{i-1}, h_0 = x) the pass down is
//!   ν_top = w_out (the output row),  α_i = (1 − h_i²) ⊙ ν_i,  ν_{i-1} = W_{i-1}ᵀ α_i,
//! and g_k = Σ_c β_c ∂φ_c/∂q_k with β = W_0ᵀ α_1 on φ's columns. Its reverse, given ḡ: β̄ = Σ_k ḡ_k ∂φ/∂q_k,
//! then up the layers ᾱ_i = W_{i-1} ν̄_{i-1}, W̄_{i-1} += α_i ν̄_{i-1}ᵀ, ν̄_i = (1 − h_i²) ⊙ ᾱ_i and
//! h̄_i = −2 h_i ⊙ ν_i ⊙ ᾱ_i (w̄_out = Σ ν̄_top); last the value path down as any tanh MLP's reverse from those h̄.
//!
//! A tile's tape: per hidden layer [h; ν; α] (t × width each), then β on φ's columns per joint (t × n × 2, laid
//! out as ∂φ/∂q) and g/v_scale (t × n).

use super::gemm::gemm;
use super::net::{dot, Net, Tile};
use crate::real::Real;

/// Values of one tile's tape for `t` samples of `n` joints.
pub(crate) fn tape_len<T: Real>(net: &Net<T>, t: usize, n: usize) -> usize {
    let hidden = &net.layers[..net.layers.len() - 1];
    3 * t * hidden.iter().map(|l| l.op).sum::<usize>() + t * n * 2 + t * n
}

/// Offset of g/v_scale (t × n) in a tile's tape.
pub(crate) fn g_offset<T: Real>(net: &Net<T>, t: usize, n: usize) -> usize {
    tape_len(net, t, n) - t * n
}

/// Offset of β (t × n × 2) in a tile's tape.
fn beta_offset<T: Real>(net: &Net<T>, t: usize, n: usize) -> usize {
    g_offset(net, t, n) - 2 * t * n
}

/// The tape's blocks of hidden layer `li`: offsets of h, ν, α.
fn blocks<T: Real>(net: &Net<T>, t: usize, li: usize) -> (usize, usize, usize) {
    let off = 3 * t * net.layers[..li].iter().map(|l| l.op).sum::<usize>();
    let w = t * net.layers[li].op;
    (off, off + w, off + 2 * w)
}

/// V's pass up (values only; V itself is not needed) and down to g, written into the tile's tape.
#[inline(always)]
pub(crate) fn forward<T: Real, const FMA: bool, const WIDE: bool>(net: &Net<T>, tile: &Tile<T>, tape: &mut [T]) {
    let t = tile.t;
    let n = tile.cols.len();
    let nh = net.layers.len() - 1;
    // up: h_i into the tape's h blocks
    for li in 0..nh {
        let layer = &net.layers[li];
        let (hb, _, _) = blocks(net, t, li);
        let op = layer.op;
        let (below, here) = tape.split_at_mut(hb);
        let h = &mut here[..t * op];
        for r in 0..t {
            h[r * op..(r + 1) * op].copy_from_slice(&layer.b);
        }
        if li == 0 {
            gemm::<T, FMA, WIDE>(t, layer.ip, op, tile.x, layer.ip, 1, &layer.wt, op, h, op, true);
        } else {
            let (pb, _, _) = blocks(net, t, li - 1);
            gemm::<T, FMA, WIDE>(t, layer.ip, op, &below[pb..pb + t * layer.ip], layer.ip, 1, &layer.wt, op, h, op, true);
        }
        T::tanh_tangent::<FMA, WIDE>(h, t * op, 1);
    }
    // down: ν_top = the output row, α_i = (1 − h²) ν_i, ν_{i-1} = α_i W_i (rows of samples)
    let out = &net.layers[nh];
    for li in (0..nh).rev() {
        let op = net.layers[li].op;
        let (hb, nb, ab) = blocks(net, t, li);
        if li == nh - 1 {
            for r in 0..t {
                tape[nb + r * op..nb + (r + 1) * op].copy_from_slice(&out.w[..op]);
            }
        }
        {
            let (lo, hi) = tape.split_at_mut(ab);
            let (h, nu) = (&lo[hb..hb + t * op], &lo[nb..nb + t * op]);
            for ((a, h), v) in hi[..t * op].iter_mut().zip(h).zip(nu) {
                *a = T::madd::<FMA>(-*h, *h, T::of(1.0)) * *v;
            }
        }
        if li > 0 {
            // ν of the layer below, which is this layer's input
            let (layer, (_, pnb, _)) = (&net.layers[li], blocks(net, t, li - 1));
            let (lo, hi) = tape.split_at_mut(ab);
            gemm::<T, FMA, WIDE>(t, op, layer.ip, &hi[..t * op], op, 1, &layer.w, layer.ip, &mut lo[pnb..pnb + t * layer.ip], layer.ip, false);
        }
    }
    // β on φ's columns and g/v_scale
    let l0 = &net.layers[0];
    let (_, _, ab) = blocks(net, t, 0);
    let bo = beta_offset(net, t, n);
    for r in 0..t {
        let alpha = &tape[ab + r * l0.op..ab + (r + 1) * l0.op];
        let mut beta = [T::default(); 2 * super::head::NMAX];
        for (k, &(ca, cb)) in tile.cols.iter().enumerate() {
            beta[2 * k] = dot::<T, FMA>(alpha, &l0.wt[ca * l0.op..(ca + 1) * l0.op]);
            if cb != usize::MAX {
                beta[2 * k + 1] = dot::<T, FMA>(alpha, &l0.wt[cb * l0.op..(cb + 1) * l0.op]);
            }
        }
        for k in 0..n {
            let i = (r * n + k) * 2;
            tape[bo + i] = beta[2 * k];
            tape[bo + i + 1] = beta[2 * k + 1];
            tape[bo + 2 * t * n + r * n + k] = T::madd::<FMA>(beta[2 * k + 1], tile.dphi[i + 1], beta[2 * k] * tile.dphi[i]);
        }
    }
}

/// Scratch of the reverse pass: per hidden layer h̄ (t × width), two t × width work rows, and the first layer's
/// weight-gradient columns of one joint (two × width).
pub(crate) struct PotBufs<T> {
    hbar: Vec<T>,
    up: Vec<T>,
    nu: Vec<T>,
    col: Vec<T>,
}

impl<T: Real> PotBufs<T> {
    pub(crate) fn new(net: &Net<T>, t: usize) -> PotBufs<T> {
        let hidden = &net.layers[..net.layers.len() - 1];
        let total = t * hidden.iter().map(|l| l.op).sum::<usize>();
        let w = t * net.width();
        let z = T::default();
        PotBufs { hbar: vec![z; total], up: vec![z; w], nu: vec![z; w], col: vec![z; 2 * net.layers[0].op] }
    }
}

/// The reverse of `forward` given ḡ/v_scale (`gbar`, t × n): this net's weight gradients added to `grad`
/// (torch's layout padded, as `net::backward`), x's to `gx` (t × ip₀) and ∂φ/∂q's to `gdphi` (t × n × 2).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward<T: Real, const FMA: bool, const WIDE: bool>(
    net: &Net<T>, tile: &Tile<T>, tape: &[T], gbar: &[T], bufs: &mut PotBufs<T>, grad: &mut [T], gx: &mut [T], gdphi: &mut [T],
) {
    let t = tile.t;
    let n = tile.cols.len();
    let nl = net.layers.len();
    let nh = nl - 1;
    let mut goff = vec![0usize; nl];
    for l in 1..nl {
        goff[l] = goff[l - 1] + net.layers[l - 1].grad_len();
    }
    let mut hoff = vec![0usize; nh];
    for l in 1..nh {
        hoff[l] = hoff[l - 1] + t * net.layers[l - 1].op;
    }
    let PotBufs { hbar, up, nu, col } = bufs;
    // β̄ on φ's columns, ∂φ/∂q's gradient, then ᾱ_1 = W_0[:, φ] β̄ and W̄_0[:, φ] += α_1 β̄ᵀ
    let l0 = &net.layers[0];
    let (op0, ip0) = (l0.op, l0.ip);
    let bo = beta_offset(net, t, n);
    let (_, _, ab0) = blocks(net, t, 0);
    let abar = &mut up[..t * op0];
    abar.fill(T::default());
    for (k, &(ca, cb)) in tile.cols.iter().enumerate() {
        col.fill(T::default());
        let (cola, colb) = col.split_at_mut(op0);
        for r in 0..t {
            let i = (r * n + k) * 2;
            let gb = gbar[r * n + k];
            gdphi[i] = T::madd::<FMA>(gb, tape[bo + i], gdphi[i]);
            let alpha = &tape[ab0 + r * op0..ab0 + (r + 1) * op0];
            let row = &mut abar[r * op0..(r + 1) * op0];
            let ba = gb * tile.dphi[i];
            for ((y, w), (c, a)) in row.iter_mut().zip(&l0.wt[ca * op0..(ca + 1) * op0]).zip(cola.iter_mut().zip(alpha)) {
                *y = T::madd::<FMA>(ba, *w, *y);
                *c = T::madd::<FMA>(ba, *a, *c);
            }
            if cb != usize::MAX {
                gdphi[i + 1] = T::madd::<FMA>(gb, tape[bo + i + 1], gdphi[i + 1]);
                let bb = gb * tile.dphi[i + 1];
                for ((y, w), (c, a)) in row.iter_mut().zip(&l0.wt[cb * op0..(cb + 1) * op0]).zip(colb.iter_mut().zip(alpha)) {
                    *y = T::madd::<FMA>(bb, *w, *y);
                    *c = T::madd::<FMA>(bb, *a, *c);
                }
            }
        }
        let dw = &mut grad[goff[0]..goff[0] + op0 * ip0];
        for o in 0..op0 {
            dw[o * ip0 + ca] = dw[o * ip0 + ca] + cola[o];
            if cb != usize::MAX {
                dw[o * ip0 + cb] = dw[o * ip0 + cb] + colb[o];
            }
        }
    }
    // up the layers: ν̄_i = (1 − h²) ᾱ_i, h̄_i = −2 h ν_i ᾱ_i, then ᾱ_{i+1} = ν̄_i W_{i+1}ᵀ, W̄_{i+1} += α_{i+1}ᵀ ν̄_i
    for li in 0..nh {
        let op = net.layers[li].op;
        let (hb, nb, _) = blocks(net, t, li);
        let hb_out = &mut hbar[hoff[li]..hoff[li] + t * op];
        let (h, nuv) = (&tape[hb..hb + t * op], &tape[nb..nb + t * op]);
        for ((((nb_, hb_), h), v), a) in nu[..t * op].iter_mut().zip(hb_out.iter_mut()).zip(h).zip(nuv).zip(&up[..t * op]) {
            *nb_ = T::madd::<FMA>(-*h, *h, T::of(1.0)) * *a;
            *hb_ = T::of(-2.0) * *h * *v * *a;
        }
        let above = &net.layers[li + 1];
        let (aip, aop) = (above.ip, above.op);
        let dw = &mut grad[goff[li + 1]..goff[li + 1] + aop * aip];
        if li + 1 == nh {
            // the output row: w̄_out += Σ_r ν̄_top
            for r in 0..t {
                for (d, x) in dw[..aip].iter_mut().zip(&nu[r * op..(r + 1) * op]) {
                    *d = *d + *x;
                }
            }
        } else {
            let (_, _, nab) = blocks(net, t, li + 1);
            gemm::<T, FMA, WIDE>(aop, t, aip, &tape[nab..nab + t * aop], 1, aop, &nu[..t * op], op, dw, aip, true);
            gemm::<T, FMA, WIDE>(t, aip, aop, &nu[..t * op], op, 1, &above.wt, aop, &mut up[..t * aop], aop, false);
        }
    }
    // the value path down from h̄: ā_i = (1 − h²) h̄_i, W̄_{i-1} += ā_iᵀ h_{i-1}, h̄_{i-1} += ā_i W_{i-1}
    for li in (0..nh).rev() {
        let layer = &net.layers[li];
        let (ip, op) = (layer.ip, layer.op);
        let (hb, _, _) = blocks(net, t, li);
        let (lower, cur) = hbar.split_at_mut(hoff[li]);
        let abar = &mut cur[..t * op];
        for (a, h) in abar.iter_mut().zip(&tape[hb..hb + t * op]) {
            *a = T::madd::<FMA>(-*h, *h, T::of(1.0)) * *a;
        }
        let (dw, rest) = grad[goff[li]..].split_at_mut(op * ip);
        let db = &mut rest[..op];
        for r in 0..t {
            for (d, x) in db.iter_mut().zip(&abar[r * op..(r + 1) * op]) {
                *d = *d + *x;
            }
        }
        if li == 0 {
            gemm::<T, FMA, WIDE>(op, t, ip, abar, 1, op, tile.x, ip, dw, ip, true);
            gemm::<T, FMA, WIDE>(t, op, ip, abar, op, 1, &layer.w, ip, gx, ip, true);
        } else {
            let (pb, _, _) = blocks(net, t, li - 1);
            gemm::<T, FMA, WIDE>(op, t, ip, abar, 1, op, &tape[pb..pb + t * ip], ip, dw, ip, true);
            let below = &mut lower[hoff[li - 1]..hoff[li - 1] + t * ip];
            gemm::<T, FMA, WIDE>(t, op, ip, abar, op, 1, &layer.w, ip, below, ip, true);
        }
    }
}
