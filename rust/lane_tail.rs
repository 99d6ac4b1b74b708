//! The dynamics tail of the lane rollouts (`lane_rollout.rs`): from the networks' outputs of a group's
//! lanes to q̈ and the next state — L and ∂L/∂q, H = LLᵀ, c, g, B, the solve, semi-implicit Euler —
//! the operations of `delan::eval_tail`, `Model::forward_after_eval` and `dynamics::solve` in `T`
//! arithmetic, each over all lanes at once (fixed-size lane arrays, so the loops vectorise).

use crate::error::Error;
use crate::lane_rollout::LaneWorkspace;
use crate::model::Model;
use crate::real::Real;

/// acc += a·b lane by lane (unfused).
#[inline(always)]
fn acc<T: Real, const L: usize>(acc: &mut [T; L], a: &[T; L], b: &[T; L]) {
    for l in 0..L {
        acc[l] = acc[l] + a[l] * b[l];
    }
}

/// The L rows of lane buffer `buf` at index e ([e][lane] layout).
#[inline(always)]
pub(crate) fn at<T: Real, const L: usize>(buf: &[T], e: usize) -> &[T; L] {
    buf[e * L..(e + 1) * L].try_into().unwrap()
}

/// q̈ of every lane from the networks' outputs (as `eval_tail` and `forward_after_eval`, in `T`;
/// each operation over all lanes at once), then semi-implicit Euler on the state. A lane whose H is
/// ill-conditioned is stopped with its error.
#[inline(always)]
pub(crate) fn step_lanes<T: Real, const L: usize>(m: &Model, lw: &mut LaneWorkspace<T>, dt: f64) {
    let (n, nn, mo) = (m.n, m.n * m.n, m.n * (m.n + 1) / 2);
    let zero = [T::default(); L];
    let (mut lm, mut dl, mut h) = ([zero; 9], [zero; 27], [zero; 9]);
    let off = T::of(m.meta.softplus_offset);
    for i in 0..n {
        let (u, mut sg, d) = (at::<T, L>(&lw.out_l, i), zero, &mut lm[i * n + i]);
        for l in 0..L {
            let (sp, s) = u[l].softplus_sigmoid();
            (d[l], sg[l]) = (sp + off, s);
        }
        for k in 0..n {
            let (du, d) = (at::<T, L>(&lw.out_l, (k + 1) * mo + i), &mut dl[k * nn + i * n + i]);
            for l in 0..L {
                d[l] = sg[l] * du[l];
            }
        }
    }
    let mut t = n;
    for i in 1..n {
        for j in 0..i {
            lm[i * n + j] = *at::<T, L>(&lw.out_l, t);
            for k in 0..n {
                dl[k * nn + i * n + j] = *at::<T, L>(&lw.out_l, (k + 1) * mo + t);
            }
            t += 1;
        }
    }
    for i in 0..n {
        for j in 0..=i {
            let mut s = zero;
            for k in 0..=j {
                acc(&mut s, &lm[i * n + k], &lm[j * n + k]);
            }
            (h[i * n + j], h[j * n + i]) = (s, s);
        }
    }
    let qd: [[T; L]; 3] = std::array::from_fn(|i| if i < n { *at::<T, L>(&lw.qd, i) } else { zero });
    // Lᵀ q̇ → t1; L̇ → ld; L̇ᵀ q̇ → t2
    let (mut t1, mut t2, mut ld) = ([zero; 3], [zero; 3], [zero; 9]);
    for j in 0..n {
        for i in j..n {
            acc(&mut t1[j], &lm[i * n + j], &qd[i]);
        }
    }
    for e in 0..nn {
        for k in 0..n {
            acc(&mut ld[e], &dl[k * nn + e], &qd[k]);
        }
    }
    for j in 0..n {
        for i in 0..n {
            acc(&mut t2[j], &ld[i * n + j], &qd[i]);
        }
    }
    let rhs = rhs_lanes::<T, L>(m, lw, &lm, &dl, &ld, &qd, &t1, &t2);
    let qdd = solve_lanes::<T, L>(n, &h, &lm, &rhs, lw);
    let dt = T::of(dt);
    for i in 0..n {
        let (q, v): (&mut [T; L], &mut [T; L]) = ((&mut lw.q[i * L..(i + 1) * L]).try_into().unwrap(), (&mut lw.qd[i * L..(i + 1) * L]).try_into().unwrap());
        for l in 0..L {
            v[l] = qd[i][l] + dt * qdd[i][l];
            q[l] = q[l] + dt * v[l];
        }
    }
}

/// τ − (c + g − B f_v) over the lanes, c = L̇ t1 + L t2 − (∂L/∂q_i ᵀ q̇)·t1.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn rhs_lanes<T: Real, const L: usize>(m: &Model, lw: &LaneWorkspace<T>, lm: &[[T; L]; 9], dl: &[[T; L]; 27], ld: &[[T; L]; 9], qd: &[[T; L]; 3], t1: &[[T; L]; 3], t2: &[[T; L]; 3]) -> [[T; L]; 3] {
    let (n, nn) = (m.n, m.n * m.n);
    let zero = [T::default(); L];
    let (vs, ls, lim) = (T::of(m.meta.v_scale), T::of(m.meta.lim_scale), m.net_lim.is_some());
    let mut rhs = [zero; 3];
    for i in 0..n {
        let (mut s, mut d) = (zero, zero);
        for j in 0..n {
            let mut w = zero;
            for a in 0..n {
                acc(&mut w, &dl[i * nn + a * n + j], &qd[a]);
            }
            let (ldij, t1j, lmij, t2j) = (&ld[i * n + j], &t1[j], &lm[i * n + j], &t2[j]);
            for l in 0..L {
                s[l] = s[l] + ldij[l] * t1j[l] + lmij[l] * t2j[l];
                d[l] = d[l] + w[l] * t1j[l];
            }
        }
        let (gv, bv, tau, fv) = (at::<T, L>(&lw.out_v, i + 1), at::<T, L>(&lw.out_b, i), at::<T, L>(&lw.tau, i), at::<T, L>(&lw.fv, 0));
        let r = &mut rhs[i];
        for l in 0..L {
            let b = if lim { ls * bv[l] } else { T::default() };
            r[l] = tau[l] - ((s[l] - d[l]) + vs * gv[l] - b * fv[l]);
        }
    }
    rhs
}

/// H⁻¹ rhs over the lanes as `dynamics::solve` (n = 1, 2 analytic; n = 3 by L); an active lane
/// beyond `T::COND_MAX` (or with det ≤ 0) is stopped with `IllConditioned`.
#[inline(always)]
fn solve_lanes<T: Real, const L: usize>(n: usize, h: &[[T; L]; 9], lm: &[[T; L]; 9], rhs: &[[T; L]; 3], lw: &mut LaneWorkspace<T>) -> [[T; L]; 3] {
    let (zero, one) = (T::default(), T::of(1.0));
    let mut out = [[zero; L]; 3];
    let (mut det, mut cond) = ([zero; L], [0.0f64; L]);
    match n {
        1 => {
            for l in 0..L {
                (det[l], out[0][l]) = (h[0][l], rhs[0][l] / h[0][l]);
            }
        }
        2 => {
            let (a, b, d) = (&h[0], &h[1], &h[3]);
            for l in 0..L {
                det[l] = a[l] * d[l] - b[l] * b[l];
                let disc = (T::of(0.25) * (a[l] - d[l]) * (a[l] - d[l]) + b[l] * b[l]).sqrt();
                let lmax = T::of(0.5) * (a[l] + d[l]) + disc;
                cond[l] = (lmax / (det[l] / lmax)).to_f64();
                let inv = one / det[l];
                out[0][l] = (d[l] * rhs[0][l] - b[l] * rhs[1][l]) * inv;
                out[1][l] = (a[l] * rhs[1][l] - b[l] * rhs[0][l]) * inv;
            }
        }
        _ => {
            for l in 0..L {
                let (mut dmin, mut dmax, mut dt) = (f64::INFINITY, 0.0f64, 1.0f64);
                for i in 0..n {
                    let d = lm[i * n + i][l].to_f64();
                    (dmin, dmax, dt) = (dmin.min(d), dmax.max(d), dt * d * d);
                }
                (det[l], cond[l]) = (T::of(dt), if dmin > 0.0 { (dmax / dmin) * (dmax / dmin) } else { f64::INFINITY });
                for i in 0..n {
                    let mut s = rhs[i][l];
                    for k in 0..i {
                        s = s - lm[i * n + k][l] * out[k][l];
                    }
                    out[i][l] = s / lm[i * n + i][l];
                }
                for i in (0..n).rev() {
                    let mut s = out[i][l];
                    for k in i + 1..n {
                        s = s - lm[k * n + i][l] * out[k][l];
                    }
                    out[i][l] = s / lm[i * n + i][l];
                }
            }
        }
    }
    for l in 0..L {
        let d = det[l].to_f64();
        if lw.active[l] && (!(d > 0.0) || !d.is_finite() || !(cond[l] <= T::COND_MAX)) {
            let c = if cond[l].is_finite() && cond[l] > 0.0 { cond[l] } else { f64::INFINITY };
            (lw.active[l], lw.status[l]) = (false, Some(Error::IllConditioned { det: d, cond: c }));
        }
    }
    out
}
