//! Batched passes with SIMD lanes across samples: up to [`LANES`] workspaces evaluated together, every
//! activation stored [block][unit][lane] (block 0 the value, block k+1 its q_k-tangent). Each hidden
//! layer is then a register-blocked small GEMM in which every weight is broadcast once for all lanes,
//! and tanh, φ's first layers and the output layers run vectorised over the lanes too.
//!
//! Each lane performs exactly the operations of `delan::eval` on its own sample, in the same order
//! (every block output's sum over the inputs in order as `mlp::block`, the last `out % 4` outputs'
//! 8 partial sums and tree as `mlp::narrow`, the same tanh), so its results are the same bits.

use crate::delan::{eval_tail, Workspace};
use crate::math::madd;
use crate::mlp::{tanh_tangent, Dense, Mlp};
use crate::model::Model;
use crate::simd::simd_dispatch;

/// Samples per group: one AVX-512 vector of f64 (two AVX2 vectors).
pub(crate) const LANES: usize = 8;
const L: usize = LANES;

/// Scratch of one group (every workspace has one; a group borrows its first member's).
#[derive(Debug, Clone, Default)]
pub(crate) struct LaneBufs {
    a: Vec<f64>,
    b: Vec<f64>,
    zin: Vec<f64>,
    zb: [Vec<f64>; 3],
    phi: Vec<f64>,
    dphi: Vec<f64>,
}

/// Whether `eval_lanes` handles this model (value + up to 3 tangents: n ≤ 3).
pub(crate) fn supported(m: &Model) -> bool {
    m.n < 4
}

fn nets(m: &Model) -> [Option<&Mlp>; 3] {
    [Some(&m.net_l), Some(&m.net_v), m.net_lim.as_ref()]
}

impl LaneBufs {
    pub(crate) fn new(m: &Model) -> LaneBufs {
        if !supported(m) {
            return LaneBufs::default();
        }
        let nt = m.n + 1;
        let widest = nets(m).iter().flatten().flat_map(|n| n.layers.iter().map(|l| l.out)).max().unwrap_or(0);
        LaneBufs {
            a: vec![0.0; nt * widest * L],
            b: vec![0.0; nt * widest * L],
            zin: vec![0.0; m.dz * L],
            zb: nets(m).map(|n| vec![0.0; n.map_or(0, |n| n.layers[0].out) * L]),
            phi: vec![0.0; m.dphi * L],
            dphi: vec![0.0; 2 * m.n * L],
        }
    }
}

/// Outputs i0..i0+R of `y = W x (+ b on block 0)` for NT blocks of LANES samples; each output's sum
/// runs over the inputs in order (b + w_0 x_0 + w_1 x_1 + …) with fused operations, as `mlp::block`.
/// SAFETY (caller): avx512f is available.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn gemm512<const NT: usize, const R: usize>(d: &Dense, x: &[f64], y: &mut [f64], i0: usize) {
    use std::arch::x86_64::*;
    let (inp, out) = (d.inp, d.out);
    assert!(x.len() >= NT * inp * L && y.len() >= NT * out * L && i0 + R <= out);
    assert!(d.wt.len() >= inp * out && d.b.len() >= out);
    let mut acc = [[_mm512_setzero_pd(); R]; NT];
    for r in 0..R {
        acc[0][r] = _mm512_set1_pd(d.b[i0 + r]);
    }
    let (wt, xp) = (d.wt.as_ptr(), x.as_ptr());
    for j in 0..inp {
        let mut xv = [_mm512_setzero_pd(); NT];
        for k in 0..NT {
            // SAFETY (all pointer reads and writes): indices are within the lengths asserted above.
            xv[k] = unsafe { _mm512_loadu_pd(xp.add((k * inp + j) * L)) };
        }
        for r in 0..R {
            let w = _mm512_set1_pd(unsafe { *wt.add(j * out + i0 + r) });
            for k in 0..NT {
                acc[k][r] = _mm512_fmadd_pd(w, xv[k], acc[k][r]);
            }
        }
    }
    for k in 0..NT {
        for r in 0..R {
            unsafe { _mm512_storeu_pd(y.as_mut_ptr().add((k * out + i0 + r) * L), acc[k][r]) };
        }
    }
}

/// `gemm512` in portable code (AVX2, SSE2): the same operations in the same order.
#[inline(always)]
fn gemm<const NT: usize, const FMA: bool, const R: usize>(d: &Dense, x: &[f64], y: &mut [f64], i0: usize) {
    let (inp, out) = (d.inp, d.out);
    let mut acc = [[[0.0f64; L]; R]; NT];
    for r in 0..R {
        acc[0][r] = [d.b[i0 + r]; L];
    }
    for j in 0..inp {
        for r in 0..R {
            let w = d.wt[j * out + i0 + r];
            for k in 0..NT {
                let xk: &[f64; L] = x[(k * inp + j) * L..(k * inp + j + 1) * L].try_into().unwrap();
                for l in 0..L {
                    acc[k][r][l] = madd::<FMA>(w, xk[l], acc[k][r][l]);
                }
            }
        }
    }
    for k in 0..NT {
        for r in 0..R {
            y[(k * out + i0 + r) * L..(k * out + i0 + r + 1) * L].copy_from_slice(&acc[k][r]);
        }
    }
}

/// The block outputs 0..nb of `dense_lanes`.
#[inline(always)]
fn gemm_range<const NT: usize, const FMA: bool, const WIDE: bool>(d: &Dense, x: &[f64], y: &mut [f64], nb: usize) {
    let mut i0 = 0;
    #[cfg(target_arch = "x86_64")]
    if WIDE {
        // SAFETY: WIDE is only instantiated inside `#[target_feature(enable = "avx512f")]` code.
        unsafe {
            // value only: 16 accumulators, enough independent FMA chains for the latency
            while NT == 1 && i0 + 16 <= nb {
                gemm512::<NT, 16>(d, x, y, i0);
                i0 += 16;
            }
            while i0 + 8 <= nb {
                gemm512::<NT, 8>(d, x, y, i0);
                i0 += 8;
            }
            while i0 < nb {
                gemm512::<NT, 1>(d, x, y, i0);
                i0 += 1;
            }
        }
    }
    while i0 + 2 <= nb {
        gemm::<NT, FMA, 2>(d, x, y, i0);
        i0 += 2;
    }
    while i0 < nb {
        gemm::<NT, FMA, 1>(d, x, y, i0);
        i0 += 1;
    }
}

/// `mlp::narrow` lane by lane for outputs i0..: `dot8` (8 partial sums, the same tree), then + b on block 0.
#[inline(always)]
fn narrow_lanes<const FMA: bool>(d: &Dense, nt: usize, x: &[f64], y: &mut [f64], i0: usize) {
    let (inp, out) = (d.inp, d.out);
    for i in i0..out {
        let wr = &d.rows[i * inp..(i + 1) * inp];
        for k in 0..nt {
            let s = dot8_lanes::<FMA>(wr, &x[k * inp * L..(k + 1) * inp * L]);
            let yi = &mut y[(k * out + i) * L..(k * out + i + 1) * L];
            for l in 0..L {
                yi[l] = if k == 0 { d.b[i] + s[l] } else { s[l] };
            }
        }
    }
}

/// `mlp::dense` for LANES samples: register blocks, then the narrow path for the last `out % 4`
/// outputs (the split every code path of `mlp::dense_nt` makes for 1–4 blocks).
#[inline(always)]
fn dense_lanes<const FMA: bool, const WIDE: bool>(d: &Dense, nt: usize, x: &[f64], y: &mut [f64]) {
    let nb = d.out - d.out % 4;
    match nt {
        1 => gemm_range::<1, FMA, WIDE>(d, x, y, nb),
        2 => gemm_range::<2, FMA, WIDE>(d, x, y, nb),
        3 => gemm_range::<3, FMA, WIDE>(d, x, y, nb),
        _ => gemm_range::<4, FMA, WIDE>(d, x, y, nb),
    }
    narrow_lanes::<FMA>(d, nt, x, y, nb);
}

/// `delan::first_layer` lane by lane: zb + W0[:, φ] φ and the tangents W0[:, φ] ∂φ/∂q_k.
#[inline(always)]
fn first_lanes<const FMA: bool>(l0: &Dense, zb: &[f64], phi: &[f64], dphi: &[f64], cols: &[(usize, usize)], nt: usize, a: &mut [f64]) {
    let h = l0.out;
    let nphi = phi.len() / L;
    for i in 0..h {
        let mut acc: [f64; L] = zb[i * L..(i + 1) * L].try_into().unwrap();
        for c in 0..nphi {
            // fixed-size views: no bounds check per lane, so the lane loops vectorise
            let (w, pc): (f64, &[f64; L]) = (l0.wt[c * h + i], phi[c * L..(c + 1) * L].try_into().unwrap());
            for l in 0..L {
                acc[l] = madd::<FMA>(w, pc[l], acc[l]);
            }
        }
        a[i * L..(i + 1) * L].copy_from_slice(&acc);
    }
    for k in 0..nt - 1 {
        let (ca, cb) = cols[k];
        let va: &[f64; L] = dphi[2 * k * L..(2 * k + 1) * L].try_into().unwrap();
        let vb: &[f64; L] = dphi[(2 * k + 1) * L..(2 * k + 2) * L].try_into().unwrap();
        for i in 0..h {
            let wa = l0.wt[ca * h + i];
            let d: &mut [f64; L] = (&mut a[((k + 1) * h + i) * L..((k + 1) * h + i + 1) * L]).try_into().unwrap();
            if cb == usize::MAX {
                for l in 0..L {
                    d[l] = wa * va[l];
                }
            } else {
                let wb = l0.wt[cb * h + i];
                for l in 0..L {
                    d[l] = madd::<FMA>(wb, vb[l], wa * va[l]);
                }
            }
        }
    }
}

/// One network over the lanes: the output layer's values and tangents end up in `a`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn net_lanes<const FMA: bool, const WIDE: bool>(net: &Mlp, zb: &[f64], phi: &[f64], dphi: &[f64], cols: &[(usize, usize)], nt: usize, a: &mut Vec<f64>, b: &mut Vec<f64>) {
    first_lanes::<FMA>(&net.layers[0], zb, phi, dphi, cols, nt, a);
    for l in 1..net.layers.len() {
        tanh_tangent::<FMA, WIDE>(a, net.layers[l - 1].out * L, nt);
        dense_lanes::<FMA, WIDE>(&net.layers[l], nt, a, b);
        std::mem::swap(a, b);
    }
}

/// `mlp::dot8` lane by lane: Σ_i w[i] x[i] with 8 partial sums (term i into sum i mod 8) and the same
/// tree. (No closures in this file's hot code: a closure does not inherit the caller's target features
/// and was compiled as a call to SSE2 code.)
#[inline(always)]
fn dot8_lanes<const FMA: bool>(w: &[f64], x: &[f64]) -> [f64; L] {
    let m = w.len();
    let mut acc = [[0.0f64; L]; 8];
    let x = &x[..m * L];
    // whole chunks of 8 with the partial index a constant once unrolled (accumulators in registers)
    let full = m / 8 * 8;
    for c in (0..full).step_by(8) {
        for p in 0..8 {
            let xi: &[f64; L] = x[(c + p) * L..(c + p + 1) * L].try_into().unwrap();
            for l in 0..L {
                acc[p][l] = madd::<FMA>(w[c + p], xi[l], acc[p][l]);
            }
        }
    }
    for p in 0..m - full {
        let xi: &[f64; L] = x[(full + p) * L..(full + p + 1) * L].try_into().unwrap();
        for l in 0..L {
            acc[p][l] = madd::<FMA>(w[full + p], xi[l], acc[p][l]);
        }
    }
    let (a, mut s) = (&acc, [0.0f64; L]);
    for l in 0..L {
        s[l] = ((a[0][l] + a[1][l]) + (a[2][l] + a[3][l])) + ((a[4][l] + a[5][l]) + (a[6][l] + a[7][l]));
    }
    s
}

/// The first layers' z parts (b + W_z z) of lanes with per-step contexts `zs`, also written to each
/// workspace as `set_z` would (z, its flag, zb_*); without `zs`, the workspaces' own are gathered.
#[inline(always)]
fn context_lanes<const FMA: bool, const WIDE: bool>(m: &Model, wss: &mut [Workspace], idx: &[usize], zs: &[&[f64]], s: &mut LaneBufs) {
    let last = idx.len() - 1;
    if zs.is_empty() {
        for l in 0..L {
            let ws = &wss[idx[l.min(last)]];
            for (t, zw) in [&ws.zb_l, &ws.zb_v, &ws.zb_lim].into_iter().enumerate() {
                for (i, v) in zw.iter().enumerate() {
                    s.zb[t][i * L + l] = *v;
                }
            }
        }
        return;
    }
    for l in 0..L {
        for (j, zj) in zs[l.min(last)].iter().enumerate() {
            s.zin[j * L + l] = *zj;
        }
    }
    for (t, net) in nets(m).iter().enumerate() {
        let Some(net) = net else { continue };
        match &net.z_part {
            Some(d) => dense_lanes::<FMA, WIDE>(d, 1, &s.zin, &mut s.zb[t]),
            None => {
                for (i, bi) in net.layers[0].b.iter().enumerate() {
                    s.zb[t][i * L..(i + 1) * L].fill(*bi);
                }
            }
        }
    }
    for (l, &w) in idx.iter().enumerate() {
        let ws = &mut wss[w];
        ws.z.copy_from_slice(zs[l]);
        ws.z_ready = true;
        for (t, zw) in [&mut ws.zb_l, &mut ws.zb_v, &mut ws.zb_lim].into_iter().enumerate() {
            for (i, v) in zw.iter_mut().enumerate() {
                *v = s.zb[t][i * L + l];
            }
        }
    }
}

/// `eval` (with c) of the workspaces `wss[idx[..]]` (1 to LANES of them, each with q in `qp` and q̇ in
/// `qdp`), lane l holding `wss[idx[l]]` (unused lanes repeat the last); `zs`: per-lane contexts to set
/// first (empty: each workspace's own). Each workspace ends as after its own `eval`, to the bit.
#[inline(always)]
fn eval_lanes<const FMA: bool, const WIDE: bool>(m: &Model, wss: &mut [Workspace], idx: &[usize], zs: &[&[f64]]) {
    let (n, nt, last) = (m.n, m.n + 1, idx.len() - 1);
    let mut s = std::mem::take(&mut wss[idx[0]].lanes);
    context_lanes::<FMA, WIDE>(m, wss, idx, zs, &mut s);
    for l in 0..L {
        let q = &wss[idx[l.min(last)]].qp;
        for (j, &(ca, cb)) in m.phi_cols.iter().enumerate() {
            let (qj, d0, d1) = (q[j], (2 * j) * L + l, (2 * j + 1) * L + l);
            if cb == usize::MAX {
                (s.phi[ca * L + l], s.dphi[d0], s.dphi[d1]) = (qj, 1.0, 0.0);
            } else {
                let (sn, cs) = qj.sin_cos();
                (s.phi[ca * L + l], s.phi[cb * L + l], s.dphi[d0], s.dphi[d1]) = (cs, sn, -sn, cs);
            }
        }
    }
    for (t, net) in nets(m).iter().enumerate() {
        let Some(net) = net else { continue };
        let ntn = if t == 2 { 1 } else { nt };
        net_lanes::<FMA, WIDE>(net, &s.zb[t], &s.phi, &s.dphi, &m.phi_cols, ntn, &mut s.a, &mut s.b);
        let out = net.d_out();
        for (l, &w) in idx.iter().enumerate() {
            let ws = &mut wss[w];
            if t == 2 {
                for i in 0..n {
                    ws.b[i] = m.meta.lim_scale * s.a[i * L + l];
                }
                continue;
            }
            let dst = if t == 0 { ws.bufs_l.last_mut() } else { ws.bufs_v.last_mut() }.unwrap();
            for e in 0..ntn * out {
                dst[e] = s.a[e * L + l];
            }
        }
    }
    wss[idx[0]].lanes = s;
    for &w in idx {
        let ws = &mut wss[w];
        let qd = std::mem::take(&mut ws.qdp);
        eval_tail(m, ws, &qd, true);
        ws.qdp = qd;
    }
}

simd_dispatch!(pub(crate) fn eval_lanes_simd(m: &Model, wss: &mut [Workspace], idx: &[usize], zs: &[&[f64]]) = eval_lanes;);
