//! Batched passes with SIMD lanes across samples: up to [`LANES`] workspaces evaluated together, every
//! activation stored [block][unit][lane] (block 0 the value, block k+1 its q_k-tangent). Each hidden
//! layer is then a register-blocked small GEMM in which every weight is broadcast once for all lanes,
//! and tanh, φ's first layers and the output layers run vectorised over the lanes too.
//!
//! Each lane performs exactly the operations of `delan::eval` on its own sample, in the same order
//! (every block output's sum over the inputs in order as `mlp::block`, the last `out % 4` outputs'
//! 8 partial sums and tree as `mlp::narrow`, the same tanh), so its results are the same bits.
//!
//! The kernels (GEMM, first layer, narrow outputs, network) are generic over [`Real`] with the lane count
//! L as a const parameter: float64 here (L = `LANES` = 8), float32 in the lane rollouts
//! (`lane_rollout.rs`, L = 16). The group pass over workspaces (`eval_lanes`) is float64 only.

use crate::delan::{eval_tail, Workspace};
use crate::mlp::{Dense, Mlp};
use crate::model::Model;
use crate::real::Real;
use crate::simd::simd_dispatch;

/// Samples per group of the float64 path: one AVX-512 vector of f64 (two AVX2 vectors).
pub(crate) const LANES: usize = 8;
const L: usize = LANES;

/// Scratch of one group (every workspace has one; a group borrows its first member's; the float32
/// lane rollouts hold a `LaneBufs<f32>`).
#[derive(Debug, Clone, Default)]
pub(crate) struct LaneBufs<T> {
    pub(crate) a: Vec<T>,
    pub(crate) b: Vec<T>,
    pub(crate) zin: Vec<T>,
    pub(crate) zb: [Vec<T>; 3],
    pub(crate) phi: Vec<T>,
    pub(crate) dphi: Vec<T>,
}

/// Whether `eval_lanes` handles this model (value + up to 3 tangents: n ≤ 3).
pub(crate) fn supported(m: &Model) -> bool {
    m.n < 4
}

impl<T: Real> LaneBufs<T> {
    pub(crate) fn new(m: &Model) -> LaneBufs<T> {
        if !supported(m) {
            return LaneBufs::default();
        }
        let (nt, lanes) = (m.n + 1, T::LANES);
        let nets = T::nets(m);
        let widest = nets.iter().flatten().flat_map(|n| n.layers.iter().map(|l| l.out)).max().unwrap_or(0);
        LaneBufs {
            a: vec![T::default(); nt * widest * lanes],
            b: vec![T::default(); nt * widest * lanes],
            zin: vec![T::default(); m.dz * lanes],
            zb: nets.map(|n| vec![T::default(); n.map_or(0, |n| n.layers[0].out) * lanes]),
            phi: vec![T::default(); m.dphi * lanes],
            dphi: vec![T::default(); 2 * m.n * lanes],
        }
    }
}

/// Outputs i0..i0+R of `y = W x (+ b on block 0)` for NT blocks of L samples (L = T::LANES: one
/// register); each output's sum runs over the inputs in order (b + w_0 x_0 + w_1 x_1 + …) with fused
/// operations, as `mlp::block`.
/// SAFETY (caller): avx512f is available.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn gemm512<T: Real, const L: usize, const NT: usize, const R: usize>(d: &Dense<T>, x: &[T], y: &mut [T], i0: usize) {
    let (inp, out) = (d.inp, d.out);
    assert!(L == T::LANES && x.len() >= NT * inp * L && y.len() >= NT * out * L && i0 + R <= out);
    assert!(d.wt.len() >= inp * out && d.b.len() >= out);
    // SAFETY (all `T::z*` calls and pointer reads and writes): avx512f (caller); indices within the
    // lengths asserted above.
    unsafe {
        let mut acc = [[T::zsplat(T::default()); R]; NT];
        for r in 0..R {
            acc[0][r] = T::zsplat(d.b[i0 + r]);
        }
        let (wt, xp) = (d.wt.as_ptr(), x.as_ptr());
        for j in 0..inp {
            let mut xv = [T::zsplat(T::default()); NT];
            for k in 0..NT {
                xv[k] = T::zload(xp.add((k * inp + j) * L));
            }
            for r in 0..R {
                let w = T::zsplat(*wt.add(j * out + i0 + r));
                for k in 0..NT {
                    acc[k][r] = T::zfmadd(w, xv[k], acc[k][r]);
                }
            }
        }
        for k in 0..NT {
            for r in 0..R {
                T::zstore(y.as_mut_ptr().add((k * out + i0 + r) * L), acc[k][r]);
            }
        }
    }
}

/// `gemm512` in portable code (AVX2, SSE2): the same operations in the same order.
#[inline(always)]
fn gemm<T: Real, const L: usize, const NT: usize, const FMA: bool, const R: usize>(d: &Dense<T>, x: &[T], y: &mut [T], i0: usize) {
    let (inp, out) = (d.inp, d.out);
    let mut acc = [[[T::default(); L]; R]; NT];
    for r in 0..R {
        acc[0][r] = [d.b[i0 + r]; L];
    }
    for j in 0..inp {
        for r in 0..R {
            let w = d.wt[j * out + i0 + r];
            for k in 0..NT {
                let xk: &[T; L] = x[(k * inp + j) * L..(k * inp + j + 1) * L].try_into().unwrap();
                for l in 0..L {
                    acc[k][r][l] = T::madd::<FMA>(w, xk[l], acc[k][r][l]);
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
fn gemm_range<T: Real, const L: usize, const NT: usize, const FMA: bool, const WIDE: bool>(d: &Dense<T>, x: &[T], y: &mut [T], nb: usize) {
    let mut i0 = 0;
    #[cfg(target_arch = "x86_64")]
    if WIDE && L == T::LANES {
        // SAFETY: WIDE is only instantiated inside `#[target_feature(enable = "avx512f")]` code.
        unsafe {
            // value only: 16 accumulators, enough independent FMA chains for the latency
            while NT == 1 && i0 + 16 <= nb {
                gemm512::<T, L, NT, 16>(d, x, y, i0);
                i0 += 16;
            }
            while i0 + 8 <= nb {
                gemm512::<T, L, NT, 8>(d, x, y, i0);
                i0 += 8;
            }
            if i0 + 4 <= nb {
                gemm512::<T, L, NT, 4>(d, x, y, i0);
                i0 += 4;
            }
            while i0 < nb {
                gemm512::<T, L, NT, 1>(d, x, y, i0);
                i0 += 1;
            }
        }
    }
    while i0 + 2 <= nb {
        gemm::<T, L, NT, FMA, 2>(d, x, y, i0);
        i0 += 2;
    }
    while i0 < nb {
        gemm::<T, L, NT, FMA, 1>(d, x, y, i0);
        i0 += 1;
    }
}

/// `mlp::narrow` lane by lane for outputs i0..: `dot8` (8 partial sums, the same tree), then + b on block 0.
#[inline(always)]
fn narrow_lanes<T: Real, const L: usize, const FMA: bool>(d: &Dense<T>, nt: usize, x: &[T], y: &mut [T], i0: usize) {
    let (inp, out) = (d.inp, d.out);
    for i in i0..out {
        let wr = &d.rows[i * inp..(i + 1) * inp];
        for k in 0..nt {
            let s = dot8_lanes::<T, L, FMA>(wr, &x[k * inp * L..(k + 1) * inp * L]);
            let yi = &mut y[(k * out + i) * L..(k * out + i + 1) * L];
            for l in 0..L {
                yi[l] = if k == 0 { d.b[i] + s[l] } else { s[l] };
            }
        }
    }
}

/// `mlp::dense` for L samples: register blocks, then the narrow path for the last `out % 4`
/// outputs (the split every code path of `mlp::dense_nt` makes for 1–4 blocks).
#[inline(always)]
pub(crate) fn dense_lanes<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(d: &Dense<T>, nt: usize, x: &[T], y: &mut [T]) {
    let nb = d.out - d.out % 4;
    match nt {
        1 => gemm_range::<T, L, 1, FMA, WIDE>(d, x, y, nb),
        2 => gemm_range::<T, L, 2, FMA, WIDE>(d, x, y, nb),
        3 => gemm_range::<T, L, 3, FMA, WIDE>(d, x, y, nb),
        _ => gemm_range::<T, L, 4, FMA, WIDE>(d, x, y, nb),
    }
    narrow_lanes::<T, L, FMA>(d, nt, x, y, nb);
}

/// `delan::first_layer` lane by lane: zb + W0[:, φ] φ and the tangents W0[:, φ] ∂φ/∂q_k.
#[inline(always)]
pub(crate) fn first_lanes<T: Real, const L: usize, const FMA: bool>(l0: &Dense<T>, zb: &[T], phi: &[T], dphi: &[T], cols: &[(usize, usize)], nt: usize, a: &mut [T]) {
    let h = l0.out;
    let nphi = phi.len() / L;
    for i in 0..h {
        let mut acc: [T; L] = zb[i * L..(i + 1) * L].try_into().unwrap();
        for c in 0..nphi {
            // fixed-size views: no bounds check per lane, so the lane loops vectorise
            let (w, pc): (T, &[T; L]) = (l0.wt[c * h + i], phi[c * L..(c + 1) * L].try_into().unwrap());
            for l in 0..L {
                acc[l] = T::madd::<FMA>(w, pc[l], acc[l]);
            }
        }
        a[i * L..(i + 1) * L].copy_from_slice(&acc);
    }
    first_tangents::<T, L, FMA>(l0, dphi, cols, nt, a);
}

/// The tangent blocks 1..nt of `first_lanes`: W0[:, φ] ∂φ/∂q_k (one or two columns per joint).
#[inline(always)]
pub(crate) fn first_tangents<T: Real, const L: usize, const FMA: bool>(l0: &Dense<T>, dphi: &[T], cols: &[(usize, usize)], nt: usize, a: &mut [T]) {
    let h = l0.out;
    for k in 0..nt - 1 {
        let (ca, cb) = cols[k];
        let va: &[T; L] = dphi[2 * k * L..(2 * k + 1) * L].try_into().unwrap();
        let vb: &[T; L] = dphi[(2 * k + 1) * L..(2 * k + 2) * L].try_into().unwrap();
        for i in 0..h {
            let wa = l0.wt[ca * h + i];
            let d: &mut [T; L] = (&mut a[((k + 1) * h + i) * L..((k + 1) * h + i + 1) * L]).try_into().unwrap();
            if cb == usize::MAX {
                for l in 0..L {
                    d[l] = wa * va[l];
                }
            } else {
                let wb = l0.wt[cb * h + i];
                for l in 0..L {
                    d[l] = T::madd::<FMA>(wb, vb[l], wa * va[l]);
                }
            }
        }
    }
}

/// One network over the lanes: the output layer's values and tangents end up in `a`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn net_lanes<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(net: &Mlp<T>, zb: &[T], phi: &[T], dphi: &[T], cols: &[(usize, usize)], nt: usize, a: &mut Vec<T>, b: &mut Vec<T>) {
    first_lanes::<T, L, FMA>(&net.layers[0], zb, phi, dphi, cols, nt, a);
    rest_lanes::<T, L, FMA, WIDE>(net, nt, a, b);
}

/// Layers 1.. of a network over the lanes from layer 0's pre-activations (with tangents) in `a`.
#[inline(always)]
pub(crate) fn rest_lanes<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(net: &Mlp<T>, nt: usize, a: &mut Vec<T>, b: &mut Vec<T>) {
    for l in 1..net.layers.len() {
        T::tanh_tangent::<FMA, WIDE>(a, net.layers[l - 1].out * L, nt);
        dense_lanes::<T, L, FMA, WIDE>(&net.layers[l], nt, a, b);
        std::mem::swap(a, b);
    }
}

/// `mlp::dot8` lane by lane: Σ_i w[i] x[i] with 8 partial sums (term i into sum i mod 8) and the same
/// tree. (No closures in this file's hot code: a closure does not inherit the caller's target features
/// and was compiled as a call to SSE2 code.)
#[inline(always)]
fn dot8_lanes<T: Real, const L: usize, const FMA: bool>(w: &[T], x: &[T]) -> [T; L] {
    let m = w.len();
    let mut acc = [[T::default(); L]; 8];
    let x = &x[..m * L];
    // whole chunks of 8 with the partial index a constant once unrolled (accumulators in registers)
    let full = m / 8 * 8;
    for c in (0..full).step_by(8) {
        for p in 0..8 {
            let xi: &[T; L] = x[(c + p) * L..(c + p + 1) * L].try_into().unwrap();
            for l in 0..L {
                acc[p][l] = T::madd::<FMA>(w[c + p], xi[l], acc[p][l]);
            }
        }
    }
    for p in 0..m - full {
        let xi: &[T; L] = x[(full + p) * L..(full + p + 1) * L].try_into().unwrap();
        for l in 0..L {
            acc[p][l] = T::madd::<FMA>(w[full + p], xi[l], acc[p][l]);
        }
    }
    let (a, mut s) = (&acc, [T::default(); L]);
    for l in 0..L {
        s[l] = ((a[0][l] + a[1][l]) + (a[2][l] + a[3][l])) + ((a[4][l] + a[5][l]) + (a[6][l] + a[7][l]));
    }
    s
}

/// The first layers' z parts (b + W_z z) of lanes with per-step contexts `zs`, also written to each
/// workspace as `set_z` would (z, its flag, zb_*); without `zs`, the workspaces' own are gathered.
#[inline(always)]
fn context_lanes<const FMA: bool, const WIDE: bool>(m: &Model, wss: &mut [Workspace], idx: &[usize], zs: &[&[f64]], s: &mut LaneBufs<f64>) {
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
    for (t, net) in f64::nets(m).iter().enumerate() {
        let Some(net) = net else { continue };
        match &net.z_part {
            Some(d) => dense_lanes::<f64, L, FMA, WIDE>(d, 1, &s.zin, &mut s.zb[t]),
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
    for (t, net) in f64::nets(m).iter().enumerate() {
        let Some(net) = net else { continue };
        let ntn = if t == 2 { 1 } else { nt };
        net_lanes::<f64, L, FMA, WIDE>(net, &s.zb[t], &s.phi, &s.dphi, &m.phi_cols, ntn, &mut s.a, &mut s.b);
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
