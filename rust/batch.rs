//! Batches on the engine's [`Pool`]: B rollouts, N independent samples, B encoder streams.
//!
//! Every element runs the same sequential code in its own workspace (or encoder state), whichever
//! thread takes it, so results are bit-identical for every thread count. Nothing here allocates:
//! the caller passes the workspaces, and the pool hands out indices without a queue.

use crate::delan::{eval_dispatch, ExoTorque, Workspace};
use crate::lanes::{self, eval_lanes_simd, LANES};
use crate::encoder::EncoderState;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::pool::{Chunks, Pool};
use crate::rollout::{Inputs, ZSeq};

fn row(x: &[f64], i: usize, n: usize) -> &[f64] {
    &x[i * n..(i + 1) * n]
}

/// Name the batch element in its input errors (numeric errors keep their own message).
pub(crate) fn in_element(b: usize, e: Error) -> Error {
    match e {
        Error::InputShape(m) => Error::InputShape(format!("batch element {b}: {m}")),
        Error::NonFiniteInput(m) => Error::NonFiniteInput(format!("batch element {b}: {m}")),
        other => other,
    }
}

/// Name the sample after the input (the message still starts with the input's name).
fn in_sample(i: usize, e: Error) -> Error {
    match e {
        Error::NonFiniteInput(m) => Error::NonFiniteInput(format!("{m} (sample {i})")),
        other => other,
    }
}

/// The error left in the first workspace that has one.
fn first_error(wss: &mut [Workspace], name: impl Fn(usize, Error) -> Error) -> Result<()> {
    let mut first = None;
    for (b, ws) in wss.iter_mut().enumerate() {
        if let Some(e) = ws.status.take() {
            first.get_or_insert_with(|| name(b, e));
        }
    }
    first.map_or(Ok(()), Err)
}

/// Optional per-sample inputs of the `*_many` calls, stacked over N samples (None: absent).
#[derive(Debug, Clone, Copy, Default)]
pub struct Samples<'a> {
    /// z, N·dz (required when the model has an encoder, else the workspace's z is kept).
    pub z: Option<&'a [f64]>,
    /// f_v, N (None: 0).
    pub f_v: Option<&'a [f64]>,
    /// τ_e, τ_app, τ̇_app, τ̈_app, N·n each (see `ExoTorque`; the last three need τ_e).
    pub tau_e: [Option<&'a [f64]>; 4],
}

impl Samples<'_> {
    fn check(&self, m: &Model, ns: usize) -> Result<()> {
        let (n, dz) = (m.n, m.dz);
        let len = |name: &str, x: Option<&[f64]>, want: usize| match x {
            Some(x) if x.len() != want => Err(Error::InputShape(format!("{name} has {} values, expected {want}", x.len()))),
            _ => Ok(()),
        };
        len("z", self.z, ns * dz)?;
        len("f_v", self.f_v, ns)?;
        for (name, x) in ["tau_e", "tau_app", "tau_app_d", "tau_app_dd"].iter().zip(self.tau_e) {
            len(name, x, ns * n)?;
        }
        if self.tau_e[0].is_none() && self.tau_e[1..].iter().any(|x| x.is_some()) {
            return Err(Error::InputShape("tau_app/tau_app_d/tau_app_dd need tau_e".into()));
        }
        Ok(())
    }

    /// Set sample i's z in `ws`; its f_v and exo torques.
    fn at<'b>(&'b self, m: &Model, ws: &mut Workspace, i: usize) -> Result<(f64, Option<ExoTorque<'b>>)> {
        let (n, dz) = (m.n, m.dz);
        if let Some(z) = self.z {
            ws.set_z(m, &z[i * dz..(i + 1) * dz])?;
        }
        let row = |x: Option<&'b [f64]>| x.map(|x| &x[i * n..(i + 1) * n]);
        let te = row(self.tau_e[0]).map(|now| ExoTorque {
            now,
            applied: row(self.tau_e[1]),
            applied_d: row(self.tau_e[2]),
            applied_dd: row(self.tau_e[3]),
        });
        Ok((self.f_v.map_or(0.0, |f| f[i]), te))
    }
}

impl Model {
    /// τ for N samples (q, qd, qdd, out: N·n) on `pool`, split over the workspaces (see `for_samples`).
    #[allow(clippy::too_many_arguments)]
    pub fn inverse_dynamics_many(
        &self,
        pool: &Pool,
        wss: &mut [Workspace],
        q: &[f64],
        qd: &[f64],
        qdd: &[f64],
        s: Samples,
        out: &mut [f64],
    ) -> Result<()> {
        let n = self.n;
        let ns = self.check_rows(&[("q", q), ("qd", qd), ("qdd", qdd)])?;
        s.check(self, ns)?;
        self.for_samples(pool, wss, ns, n, out, |ws, i, o| {
            let (f_v, te) = s.at(self, ws, i)?;
            self.inverse_dynamics(ws, row(q, i, n), row(qd, i, n), row(qdd, i, n), f_v, te, o)
        })
    }

    /// q̈ for N samples (q, qd, tau, out: N·n); only τ_e and τ_app of `s.tau_e` are read.
    #[allow(clippy::too_many_arguments)]
    pub fn forward_dynamics_many(
        &self,
        pool: &Pool,
        wss: &mut [Workspace],
        q: &[f64],
        qd: &[f64],
        tau: &[f64],
        s: Samples,
        out: &mut [f64],
    ) -> Result<()> {
        let n = self.n;
        let ns = self.check_rows(&[("q", q), ("qd", qd), ("tau", tau)])?;
        s.check(self, ns)?;
        self.for_samples(pool, wss, ns, n, out, |ws, i, o| {
            let (f_v, te) = s.at(self, ws, i)?;
            let te = te.map(|t| ExoTorque { applied_d: None, applied_dd: None, ..t });
            self.forward_dynamics(ws, row(q, i, n), row(qd, i, n), row(tau, i, n), f_v, te, o)
        })
    }

    /// [H (n·n), c, g, B (n each)] per sample for N samples: out N·(n·n + 3n).
    pub fn terms_many(&self, pool: &Pool, wss: &mut [Workspace], q: &[f64], qd: &[f64], z: Option<&[f64]>, out: &mut [f64]) -> Result<()> {
        let n = self.n;
        let ns = self.check_rows(&[("q", q), ("qd", qd)])?;
        let s = Samples { z, ..Default::default() };
        s.check(self, ns)?;
        self.for_samples(pool, wss, ns, n * n + 3 * n, out, |ws, i, o| {
            s.at(self, ws, i)?;
            self.terms(ws, &q[i * n..(i + 1) * n], &qd[i * n..(i + 1) * n])?;
            let (h, rest) = o.split_at_mut(n * n);
            h.copy_from_slice(ws.h());
            rest[..n].copy_from_slice(ws.c());
            rest[n..2 * n].copy_from_slice(ws.g());
            rest[2 * n..].copy_from_slice(ws.b());
            Ok(())
        })
    }

    /// N from equal-length N·n arrays.
    fn check_rows(&self, rows: &[(&str, &[f64])]) -> Result<usize> {
        let n = self.n;
        let len = rows[0].1.len();
        for (name, x) in rows {
            if x.len() != len || x.len() % n != 0 {
                return Err(Error::InputShape(format!("{name} has {} values, expected N·n = {len} (n = {n})", x.len())));
            }
        }
        Ok(len / n)
    }

    /// B independent rollouts on `pool`, one workspace each (`wss.len() == B`). Shapes:
    /// q0, qd0 B·n; tau B·T·n; z Const B·dz or PerStep B·T·dz; f_v B·T; tau_e B·T·n;
    /// outputs B·(T+1)·n. The first failing element (lowest index) decides the error.
    #[allow(clippy::too_many_arguments)]
    pub fn rollout_batch(
        &self,
        pool: &Pool,
        wss: &mut [Workspace],
        q0: &[f64],
        qd0: &[f64],
        inp: Inputs,
        dt: f64,
        q_out: &mut [f64],
        qd_out: &mut [f64],
    ) -> Result<()> {
        let (n, bsz) = (self.n, wss.len());
        if bsz == 0 {
            return Ok(());
        }
        let t_len = self.check_batch(bsz, q0, qd0, &inp, q_out, qd_out)?;
        let per_out = (t_len + 1) * n;
        let g = LANES;
        let (wsc, qc, qdc) = (Chunks::new(wss, g), Chunks::new(q_out, g * per_out), Chunks::new(qd_out, g * per_out));
        pool.run(bsz.div_ceil(g), &|task| {
            // SAFETY: the pool hands each index to exactly one task.
            let (ws, qo, qdo) = unsafe { (wsc.get(task), qc.get(task), qdc.get(task)) };
            self.rollout_group(task * g, ws, q0, qd0, &inp, t_len, dt, qo, qdo);
        });
        first_error(wss, in_element)
    }

    /// Elements b0.. of a batch (one per workspace) stepped together, one SIMD lane each (`lanes.rs`:
    /// every weight passes once per step for the group); an element that fails leaves the group (its
    /// error in its workspace) and the others go on, each computing exactly what its own rollout would.
    #[allow(clippy::too_many_arguments)]
    fn rollout_group(&self, b0: usize, wss: &mut [Workspace], q0: &[f64], qd0: &[f64], inp: &Inputs, t_len: usize, dt: f64, qo: &mut [f64], qdo: &mut [f64]) {
        let (n, dz) = (self.n, self.dz);
        let per_out = (t_len + 1) * n;
        let mut active = [false; LANES];
        let mut subs = [*inp; LANES];
        for (e, ws) in wss.iter_mut().enumerate() {
            let b = b0 + e;
            subs[e] = Inputs {
                tau: &inp.tau[b * t_len * n..(b + 1) * t_len * n],
                z: match inp.z {
                    ZSeq::Keep => ZSeq::Keep,
                    ZSeq::Const(z) => ZSeq::Const(&z[b * dz..(b + 1) * dz]),
                    ZSeq::PerStep(z) => ZSeq::PerStep(&z[b * t_len * dz..(b + 1) * t_len * dz]),
                },
                f_v: inp.f_v.map(|f| &f[b * t_len..(b + 1) * t_len]),
                tau_e: inp.tau_e.map(|f| &f[b * t_len * n..(b + 1) * t_len * n]),
            };
            let out = e * per_out..(e + 1) * per_out;
            let r = self.rollout_begin(ws, &q0[b * n..(b + 1) * n], &qd0[b * n..(b + 1) * n], &subs[e], dt, &mut qo[out.clone()], &mut qdo[out]);
            active[e] = r.is_ok();
            ws.status = r.err();
        }
        let grouped = lanes::supported(self);
        // per-step contexts (checked by rollout_begin) are set in lanes, with the pass
        let z_set = grouped && matches!(inp.z, ZSeq::PerStep(_));
        for k in 0..t_len {
            for (e, ws) in wss.iter_mut().enumerate() {
                if !active[e] {
                    continue;
                }
                let out = e * per_out..(e + 1) * per_out;
                if let Err(err) = self.step_begin(ws, &subs[e], k, dt, &qo[out.clone()], &qdo[out], z_set) {
                    (active[e], ws.status) = (false, Some(err));
                }
            }
            let (mut idx, mut zs, mut cnt) = ([0usize; LANES], [&[][..]; LANES], 0);
            for e in (0..wss.len()).filter(|e| active[*e]) {
                if let ZSeq::PerStep(z) = subs[e].z {
                    zs[cnt] = &z[k * dz..(k + 1) * dz];
                }
                (idx[cnt], cnt) = (e, cnt + 1);
            }
            if cnt == 0 {
                break;
            }
            if grouped {
                eval_lanes_simd(self.simd, self, wss, &idx[..cnt], if z_set { &zs[..cnt] } else { &[] });
            } else {
                for &e in &idx[..cnt] {
                    let ws = &mut wss[e];
                    let qd = std::mem::take(&mut ws.qdp);
                    eval_dispatch(self, ws, &qd, true);
                    ws.qdp = qd;
                }
            }
            for &e in &idx[..cnt] {
                let out = e * per_out..(e + 1) * per_out;
                if let Err(err) = self.step_end(&mut wss[e], &subs[e], k, dt, &mut qo[out.clone()], &mut qdo[out]) {
                    (active[e], wss[e].status) = (false, Some(err));
                }
            }
        }
    }

    /// The batch shapes of `rollout_batch`; returns T.
    pub(crate) fn check_batch(&self, bsz: usize, q0: &[f64], qd0: &[f64], inp: &Inputs, q_out: &[f64], qd_out: &[f64]) -> Result<usize> {
        let (n, dz) = (self.n, self.dz);
        if q0.len() != bsz * n || qd0.len() != bsz * n {
            return Err(Error::InputShape(format!("q0 and qd0 must hold B·n = {} values", bsz * n)));
        }
        if !inp.tau.len().is_multiple_of(bsz * n) {
            return Err(Error::InputShape(format!("tau has {} values, not B·T·n with B = {bsz}, n = {n}", inp.tau.len())));
        }
        let t_len = inp.tau.len() / (bsz * n);
        let per_out = (t_len + 1) * n;
        if q_out.len() != bsz * per_out || qd_out.len() != bsz * per_out {
            return Err(Error::InputShape(format!("outputs must hold B·(T+1)·n = {} values", bsz * per_out)));
        }
        match inp.z {
            ZSeq::Const(z) if z.len() != bsz * dz => {
                return Err(Error::InputShape(format!("z has {} values, expected B·dz = {}", z.len(), bsz * dz)))
            }
            ZSeq::PerStep(z) if z.len() != bsz * t_len * dz => {
                return Err(Error::InputShape(format!("z has {} values, expected B·T·dz = {}", z.len(), bsz * t_len * dz)))
            }
            _ => {}
        }
        if inp.f_v.is_some_and(|f| f.len() != bsz * t_len) {
            return Err(Error::InputShape(format!("f_v must hold B·T = {} values", bsz * t_len)));
        }
        if inp.tau_e.is_some_and(|f| f.len() != bsz * t_len * n) {
            return Err(Error::InputShape(format!("tau_e must hold B·T·n = {} values", bsz * t_len * n)));
        }
        Ok(t_len)
    }

    /// `f(ws, i, out_i)` for every sample i in 0..N, `out` holding N·width values: the samples are
    /// split into `wss.len()` contiguous runs, one per workspace, spread over `pool`. The first
    /// failing sample (lowest index) decides the error.
    #[allow(clippy::too_many_arguments)]
    pub fn for_samples<F>(&self, pool: &Pool, wss: &mut [Workspace], n_samples: usize, width: usize, out: &mut [f64], f: F) -> Result<()>
    where
        F: Fn(&mut Workspace, usize, &mut [f64]) -> Result<()> + Sync,
    {
        if out.len() != n_samples * width {
            return Err(Error::InputShape(format!("output holds {} values, expected {}", out.len(), n_samples * width)));
        }
        if n_samples == 0 || wss.is_empty() {
            return Ok(());
        }
        let per = n_samples.div_ceil(wss.len());
        let tasks = n_samples.div_ceil(per);
        let (wsc, oc) = (Chunks::new(wss, 1), Chunks::new(out, per * width));
        pool.run(tasks, &|t| {
            // SAFETY: the pool hands each index t to exactly one task.
            let (ws, o) = unsafe { (&mut wsc.get(t)[0], oc.get(t)) };
            ws.status = o
                .chunks_mut(width)
                .enumerate()
                .try_for_each(|(r, o_i)| f(ws, t * per + r, o_i).map_err(|e| in_sample(t * per + r, e)))
                .err();
        });
        first_error(wss, |_, e| e)
    }

    /// Stream B sequences of raw context samples (x: B·T·C) through the encoder, each from the
    /// state it is in (`states.len() == B`; reset them for a trial start); z_out: B·T·dz.
    pub fn encode_batch(&self, pool: &Pool, states: &mut [EncoderState], x: &[f64], z_out: &mut [f64]) -> Result<()> {
        let (c, dz, bsz) = (self.context_dim(), self.dz, states.len());
        if bsz == 0 {
            return Ok(());
        }
        if c == 0 || !x.len().is_multiple_of(bsz * c) {
            return Err(Error::InputShape(format!("x has {} values, not B·T·C with B = {bsz}, C = {c}", x.len())));
        }
        let t_len = x.len() / (bsz * c);
        if z_out.len() != bsz * t_len * dz {
            return Err(Error::InputShape(format!("z output must hold B·T·dz = {} values", bsz * t_len * dz)));
        }
        let (sc, zc) = (Chunks::new(states, 1), Chunks::new(z_out, t_len * dz));
        pool.run(bsz, &|b| {
            // SAFETY: the pool hands each index b to exactly one task.
            let (st, zb) = unsafe { (&mut sc.get(b)[0], zc.get(b)) };
            for t in 0..t_len {
                let o = (b * t_len + t) * c;
                // shapes are checked above; the only errors are per-model and show on element 0 too
                if let Err(e) = self.encode_step(st, &x[o..o + c], &mut zb[t * dz..(t + 1) * dz]) {
                    st.status = Some(e);
                    return;
                }
            }
        });
        for st in states.iter_mut() {
            if let Some(e) = st.status.take() {
                return Err(e);
            }
        }
        Ok(())
    }
}
