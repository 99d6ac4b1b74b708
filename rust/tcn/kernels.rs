//! The per-chunk passes of the TCN encoder (`super`): forward and reverse through each sequence's blocks.
//! Every function here is `#[inline(always)]` down from the SIMD dispatch, so that it is compiled with the
//! level's target features (an out-of-line call would turn every fused multiply-add into a libm call).

use super::{Block, BwdJob, Conv, FwdJob, Tcn};
use crate::grad::gemm::gemm;
use crate::real::Real;

/// Rows of `gemm`'s register block: weight gradients are computed in whole blocks (`wgrad`).
const MR: usize = 6;

#[inline(always)]
fn relu<T: Real>(v: T) -> T {
    if v > T::default() { v } else { T::default() }
}

/// a (t × op) = Σ_k Wₖ x[· − shiftₖ] without the bias (added by the activation pass), x (t × cin, row stride
/// sx) zero before its first row. The unshifted tap (the last) covers every row, so it starts the sum.
#[inline(always)]
fn conv_forward<T: Real, const FMA: bool, const WIDE: bool>(c: &Conv<T>, t: usize, x: &[T], sx: usize, a: &mut [T]) {
    let op = c.op;
    for k in (0..c.taps).rev() {
        let s = c.shift(k);
        if s < t {
            gemm::<T, FMA, WIDE>(t - s, c.cin, op, x, sx, 1, &c.wt[k * c.cin * op..], op, &mut a[s * op..], op, k + 1 < c.taps);
        }
    }
}

/// dW (m × w, row stride w) += Σ_j a[r + j·acs] · B[j] with A read transposed, in whole register blocks: where
/// m is no multiple of MR, the last MR rows are a second product into `tmp` whose rows past the first
/// product's are added (gemm's one-row tail is a chain of dependent fused operations, about 4x slower per row).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn wgrad<T: Real, const FMA: bool, const WIDE: bool>(
    m: usize, k: usize, w: usize, a: &[T], acs: usize, b: &[T], ldb: usize, dw: &mut [T], tmp: &mut [T],
) {
    let main = m / MR * MR;
    if main == 0 || main == m {
        gemm::<T, FMA, WIDE>(m, k, w, a, 1, acs, b, ldb, dw, w, true);
        return;
    }
    gemm::<T, FMA, WIDE>(main, k, w, a, 1, acs, b, ldb, dw, w, true);
    gemm::<T, FMA, WIDE>(MR, k, w, &a[m - MR..], 1, acs, b, ldb, tmp, w, false);
    for (d, v) in dw[main * w..m * w].iter_mut().zip(&tmp[(MR - (m - main)) * w..MR * w]) {
        *d = *d + *v;
    }
}

/// The reverse of `conv_forward` over one sequence from ga (t × op): dWₖ added to `dw`; with `gx`, the input
/// gradient (t × cip) written there, or added to it with `acc`. `tmp`: MR × cip values of scratch.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn conv_backward<T: Real, const FMA: bool, const WIDE: bool>(
    c: &Conv<T>, t: usize, ga: &[T], x: &[T], sx: usize, dw: &mut [T], tmp: &mut [T], gx: Option<&mut [T]>, acc: bool,
) {
    let (cout, cip, op) = (c.cout, c.cip, c.op);
    for k in 0..c.taps {
        let s = c.shift(k);
        if s < t {
            // dWₖ = Σ_t ga[t] ⊗ x[t − s]: x's padded columns are zero, so is the product's padding
            wgrad::<T, FMA, WIDE>(cout, t - s, cip, &ga[s * op..], op, x, sx, &mut dw[k * cout * cip..(k + 1) * cout * cip], tmp);
        }
    }
    if let Some(gx) = gx {
        for k in (0..c.taps).rev() {
            let s = c.shift(k);
            if s < t {
                let acc = acc || k + 1 < c.taps;
                gemm::<T, FMA, WIDE>(t - s, cout, cip, &ga[s * op..], op, 1, &c.w[k * cout * cip..], cip, gx, cip, acc);
            }
        }
    }
}

/// One block over one sequence: h₁, y (t × hp each) and h₂'s ReLU mask `m` from x (t × cin, row stride sx);
/// a₂ (t × hp) is scratch. The elementwise passes go in register-wide pieces (`T::LANES` ≤ 16, a constant: each
/// inner loop one vector operation), computed into a local array and then stored, as a store into the row could
/// otherwise alias the next loads (the loop would stay scalar).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn block_forward<T: Real, const FMA: bool, const WIDE: bool>(
    b: &Block<T>, t: usize, x: &[T], sx: usize, keep: &[T], h1: &mut [T], a2: &mut [T], y: &mut [T], m: &mut [u8],
) {
    let (hp, nl, z) = (b.conv2.op, T::LANES, T::default());
    let (mut v, mut w, mut mb) = ([z; 16], [z; 16], [0u8; 16]);
    // columns outside, rows inside: a row is one vector for hidden ≤ LANES, and the loop over rows stays tight
    conv_forward::<T, FMA, WIDE>(&b.conv1, t, x, sx, h1);
    for c in (0..hp).step_by(nl) {
        let b1 = &b.conv1.b[c..c + nl];
        for r in 0..t {
            let (a, kr) = (&h1[r * hp + c..r * hp + c + nl], keep[r]);
            for l in 0..nl {
                v[l] = relu(a[l] + b1[l]) * kr;
            }
            h1[r * hp + c..r * hp + c + nl].copy_from_slice(&v[..nl]);
        }
    }
    conv_forward::<T, FMA, WIDE>(&b.conv2, t, h1, hp, a2);
    // h₂ = relu(a₂ + b₂), its mask, and y = relu(h₂ + res(x))·keep in one pass: res(x) = (r + b_r), r in y, or x
    if let Some(c) = &b.res {
        conv_forward::<T, FMA, WIDE>(c, t, x, sx, y);
    }
    for c in (0..hp).step_by(nl) {
        let b2 = &b.conv2.b[c..c + nl];
        let br = b.res.as_ref().map(|res| &res.b[c..c + nl]);
        for r in 0..t {
            let (i, kr) = (r * hp + c, keep[r]);
            let a = &a2[i..i + nl];
            for l in 0..nl {
                v[l] = relu(a[l] + b2[l]);
                mb[l] = u8::from(v[l] > z);
            }
            match br {
                Some(br) => {
                    let rv = &y[i..i + nl];
                    for l in 0..nl {
                        w[l] = relu(v[l] + (rv[l] + br[l])) * kr;
                    }
                }
                None => {
                    let xv = &x[r * sx + c..r * sx + c + nl];
                    for l in 0..nl {
                        w[l] = relu(v[l] + xv[l]) * kr;
                    }
                }
            }
            m[i..i + nl].copy_from_slice(&mb[..nl]);
            y[i..i + nl].copy_from_slice(&w[..nl]);
        }
    }
}

/// ReLU's reverse from its saved output `o` (torch's rule: the gradient passes where o > 0): g = g there and 0
/// elsewhere, in place, Σ_t g added to `db` where given; with `then` = (m, ga, db_a), also ga = g where the mask
/// m is set and Σ_t ga added to db_a. Columns go in register-wide pieces outside and rows inside, so that the
/// sums stay in registers; values are computed into local arrays, then stored (see `block_forward`), and loaded
/// ahead of each comparison, as a conditional load compiles to a branch per value.
#[inline(always)]
fn relu_back<T: Real>(t: usize, op: usize, o: &[T], g: &mut [T], db: Option<&mut [T]>, then: Option<(&[u8], &mut [T], &mut [T])>) {
    let (nl, z) = (T::LANES, T::default());
    let (mut db, mut then) = (db, then);
    for c in (0..op).step_by(nl) {
        let (mut sum, mut sum_a, mut v, mut a) = ([z; 16], [z; 16], [z; 16], [z; 16]);
        for r in 0..t {
            let i = r * op + c;
            let (orow, gr) = (&o[i..i + nl], &g[i..i + nl]);
            for l in 0..nl {
                let gv = gr[l];
                v[l] = if orow[l] > z { gv } else { z };
                sum[l] = sum[l] + v[l];
            }
            g[i..i + nl].copy_from_slice(&v[..nl]);
            if let Some((m, ga, _)) = then.as_mut() {
                let mr = &m[i..i + nl];
                for l in 0..nl {
                    a[l] = if mr[l] != 0 { v[l] } else { z };
                    sum_a[l] = sum_a[l] + a[l];
                }
                ga[i..i + nl].copy_from_slice(&a[..nl]);
            }
        }
        if let Some(db) = db.as_deref_mut() {
            for l in 0..nl {
                db[c + l] = db[c + l] + sum[l];
            }
        }
        if let Some((_, _, db_a)) = then.as_mut() {
            for l in 0..nl {
                db_a[c + l] = db_a[c + l] + sum_a[l];
            }
        }
    }
}

/// One block's reverse over one sequence: gy (the gradient of y) in, overwritten; the block's weight gradients
/// added to `grad`; with `want_gx`, the gradient of x written into `ga2`'s buffer, spent by then. ga₂, ga₁:
/// t × max(hp, cip) values of scratch.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn block_backward<T: Real, const FMA: bool, const WIDE: bool>(
    b: &Block<T>, t: usize, x: &[T], sx: usize, tape: (&[T], &[T], &[u8]), gy: &mut [T], ga2: &mut [T], ga1: &mut [T],
    want_gx: bool, grad: &mut [T], tmp: &mut [T],
) {
    let (h1, y, m2) = tape;
    let hp = b.conv2.op;
    let (c1, c2) = (&b.conv1, &b.conv2);
    let (dw1, rest) = grad.split_at_mut(c1.taps * c1.cout * c1.cip);
    let (db1, rest) = rest.split_at_mut(c1.op);
    let (dw2, rest) = rest.split_at_mut(c2.taps * c2.cout * c2.cip);
    let (db2, rest) = rest.split_at_mut(c2.op);
    let (dwr, dbr) = rest.split_at_mut(rest.len().saturating_sub(hp));
    let (gy, ga1) = (&mut gy[..t * hp], &mut ga1[..t * hp]);
    // y = relu(h₂ + res(x))·keep, then h₂ = relu(a₂): gy becomes the gradient of res(x), ga₂ that of a₂
    relu_back(t, hp, y, gy, b.res.is_some().then_some(dbr), Some((m2, &mut ga2[..t * hp], db2)));
    conv_backward::<T, FMA, WIDE>(c2, t, &ga2[..t * hp], h1, hp, dw2, tmp, Some(&mut *ga1), false);
    // h₁ = relu(a₁)·keep
    relu_back(t, hp, h1, ga1, Some(db1), None);
    let mut gx = want_gx.then_some(&mut ga2[..t * sx]);
    conv_backward::<T, FMA, WIDE>(c1, t, ga1, x, sx, dw1, tmp, gx.as_deref_mut(), false);
    match &b.res {
        Some(c) => conv_backward::<T, FMA, WIDE>(c, t, gy, x, sx, dwr, tmp, gx, true),
        None => {
            if let Some(gx) = gx {
                let mut v = [T::default(); 16];
                for (d, g) in gx.chunks_exact_mut(T::LANES).zip(gy.chunks_exact(T::LANES)) {
                    for l in 0..T::LANES {
                        v[l] = d[l] + g[l];
                    }
                    d.copy_from_slice(&v[..T::LANES]);
                }
            }
        }
    }
}

/// The first `w` of every `sw` values of `src` into `dst`: one copy when there is no padding (a copy per row
/// is a library call per row).
#[inline(always)]
fn first_cols<T: Real>(src: &[T], sw: usize, dst: &mut [T], w: usize) {
    if w == sw {
        dst.copy_from_slice(&src[..dst.len()]);
    } else {
        for (d, s) in dst.chunks_exact_mut(w).zip(src.chunks_exact(sw)) {
            d.copy_from_slice(&s[..w]);
        }
    }
}

/// A sequence's forward pass into its tape `st` and masks `sm` (layout: `Tcn::seq_len`, `Tcn::mask_len`); a₂:
/// t × hp of scratch.
#[inline(always)]
fn seq_forward<T: Real, const FMA: bool, const WIDE: bool>(
    k: &Tcn<T>, t: usize, x: &[T], keep: &[T], st: &mut [T], sm: &mut [u8], a2: &mut [T],
) {
    let (c_in, cip, hp) = (k.c_in, k.cip, k.hp);
    let (x0, mut rest) = st.split_at_mut(t * cip);
    x0.fill(T::default());
    for ((row, xr), &kr) in x0.chunks_exact_mut(cip).zip(x.chunks_exact(c_in)).zip(keep) {
        for (v, xv) in row.iter_mut().zip(xr) {
            *v = *xv * kr;
        }
    }
    let (mut input, mut sx): (&[T], usize) = (x0, cip);
    for (b, m) in k.blocks.iter().zip(sm.chunks_exact_mut(t * hp)) {
        let (h1, r) = std::mem::take(&mut rest).split_at_mut(t * hp);
        let (y, r) = r.split_at_mut(t * hp);
        block_forward::<T, FMA, WIDE>(b, t, input, sx, keep, h1, a2, y, m);
        (input, sx, rest) = (y, hp, r);
    }
}

#[inline(always)]
pub(super) fn forward_chunk<T: Real, const FMA: bool, const WIDE: bool>(
    job: &FwdJob<T>, ci: usize, tape: &mut [T], masks: &mut [u8], z: &mut [T],
) {
    let (k, t) = (job.k, job.t_len);
    let (sl, ml, h, hp, c_in) = (k.seq_len(t), k.mask_len(t), k.hidden, k.hp, k.c_in);
    let first = ci * job.spc;
    let count = (job.batch - first).min(job.spc);
    let mut a2 = vec![T::default(); t * hp];
    // without a tape, one sequence's worth of it is reused sequence after sequence
    let (mut own, mut own_masks) = if job.tape { (Vec::new(), Vec::new()) } else { (vec![T::default(); sl], vec![0; ml]) };
    for j in 0..count {
        let s = first + j;
        let (st, sm) = if job.tape {
            (&mut tape[j * sl..(j + 1) * sl], &mut masks[j * ml..(j + 1) * ml])
        } else {
            (&mut own[..], &mut own_masks[..])
        };
        seq_forward::<T, FMA, WIDE>(k, t, &job.x[s * t * c_in..(s + 1) * t * c_in], &job.keep[s * t..(s + 1) * t], st, sm, &mut a2);
        first_cols(&st[sl - t * hp..], hp, &mut z[j * t * h..(j + 1) * t * h], h);
    }
}

/// A sequence's reverse pass from its tape `st`, masks `sm` and the gradient of its z; `bufs`: 3 · t · max(hp, cip)
/// values of scratch, `tmp`: MR · max(hp, cip).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn seq_backward<T: Real, const FMA: bool, const WIDE: bool>(
    k: &Tcn<T>, t: usize, st: &[T], sm: &[u8], gz: &[T], keep: &[T], grad: &mut [T], dx: Option<&mut [T]>, bufs: &mut [T],
    tmp: &mut [T],
) {
    let (h, hp, cip) = (k.hidden, k.hp, k.cip);
    let w = hp.max(cip);
    let (mut gy, rest) = bufs.split_at_mut(t * w);
    let (mut ga2, ga1) = rest.split_at_mut(t * w);
    if h == hp {
        gy[..t * h].copy_from_slice(gz);
    } else {
        gy.fill(T::default());
        for (g, zr) in gy.chunks_exact_mut(hp).zip(gz.chunks_exact(h)) {
            g[..h].copy_from_slice(zr);
        }
    }
    let mut goff = grad.len();
    for (i, b) in k.blocks.iter().enumerate().rev() {
        goff -= b.grad_len();
        let base = t * cip + 2 * i * t * hp;
        let tape = (&st[base..][..t * hp], &st[base + t * hp..][..t * hp], &sm[i * t * hp..(i + 1) * t * hp]);
        let (x, sx) = if i == 0 { (&st[..t * cip], cip) } else { (&st[base - t * hp..base], hp) };
        let g = &mut grad[goff..goff + b.grad_len()];
        block_backward::<T, FMA, WIDE>(b, t, x, sx, tape, gy, ga2, ga1, i > 0 || dx.is_some(), g, tmp);
        // x's gradient, in ga₂'s buffer, is the next block's gy
        std::mem::swap(&mut gy, &mut ga2);
    }
    // the input was multiplied by keep
    if let Some(dx) = dx {
        for ((d, g), &kr) in dx.chunks_exact_mut(k.c_in).zip(gy.chunks_exact(cip)).zip(keep) {
            for (dv, gv) in d.iter_mut().zip(g) {
                *dv = *gv * kr;
            }
        }
    }
}

#[inline(always)]
pub(super) fn backward_chunk<T: Real, const FMA: bool, const WIDE: bool>(job: &BwdJob<T>, ci: usize, grad: &mut [T], dx: &mut [T]) {
    let (k, tape) = (job.k, job.tape);
    let t = tape.t_len;
    let (sl, ml, w, h, c_in) = (k.seq_len(t), k.mask_len(t), k.hp.max(k.cip), k.hidden, k.c_in);
    let mut bufs = vec![T::default(); 3 * t * w];
    let mut tmp = vec![T::default(); MR * w];
    let first = ci * job.spc;
    let count = (tape.batch - first).min(job.spc);
    for j in 0..count {
        let s = first + j;
        let dxs = if job.dx { Some(&mut dx[j * t * c_in..(j + 1) * t * c_in]) } else { None };
        let (st, sm) = (&tape.data[s * sl..(s + 1) * sl], &tape.masks[s * ml..(s + 1) * ml]);
        let (gz, keep) = (&job.gz[s * t * h..(s + 1) * t * h], &tape.keep[s * t..(s + 1) * t]);
        seq_backward::<T, FMA, WIDE>(k, t, st, sm, gz, keep, grad, dxs, &mut bufs, &mut tmp);
    }
}
