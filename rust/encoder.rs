//! Streaming context encoders: one raw sample in, z out (DESIGN.md section 2, "Encoders").
//!
//! Causal TCN: each conv of dilation d and kernel k needs its input at t, t−d, …, t−(k−1)d, kept in
//! a ring buffer of (k−1)·d + 1 slots per conv; zero-initialised rings are exactly torch's left zero
//! padding. LSTM: the (h, c) state per layer. Both start from zero state, as a trial does in torch.

use crate::error::{Error, Result};
use crate::math::{madd, sigmoid, tanh};
use crate::mlp::Dense;
use crate::model::Model;

#[derive(Debug, Clone)]
pub struct TcnBlock {
    pub dil: usize,
    pub kernel: usize,
    pub cin: usize,
    pub cout: usize,
    /// One dense map per tap (no bias); tap t multiplies x[now − (k−1−t)·d].
    conv1: Vec<Dense>,
    b1: Vec<f64>,
    conv2: Vec<Dense>,
    b2: Vec<f64>,
    res: Option<Dense>,
}

fn taps(w: &[f64], cout: usize, cin: usize, k: usize) -> Vec<Dense> {
    (0..k)
        .map(|t| {
            let rows: Vec<f64> = (0..cout * cin).map(|oi| w[oi * k + t]).collect();
            Dense::from_rows(&rows, &vec![0.0; cout], cout, cin)
        })
        .collect()
}

impl TcnBlock {
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        dil: usize,
        kernel: usize,
        cin: usize,
        cout: usize,
        w1: &[f64],
        b1: &[f64],
        w2: &[f64],
        b2: &[f64],
        res: Option<Dense>,
    ) -> TcnBlock {
        TcnBlock {
            dil,
            kernel,
            cin,
            cout,
            conv1: taps(w1, cout, cin, kernel),
            b1: b1.to_vec(),
            conv2: taps(w2, cout, cout, kernel),
            b2: b2.to_vec(),
            res,
        }
    }
    fn slots(&self) -> usize {
        (self.kernel - 1) * self.dil + 1
    }
}

#[derive(Debug, Clone)]
pub struct Tcn {
    pub blocks: Vec<TcnBlock>,
    pub c_in: usize,
}

#[derive(Debug, Clone)]
pub struct LstmLayer {
    pub inp: usize,
    pub hidden: usize,
    /// [W_ih | W_hh] (4H × (inp + H)), bias b_ih + b_hh; gate order i, f, g, o.
    cell: Dense,
}

impl LstmLayer {
    pub(crate) fn new(inp: usize, hidden: usize, wih: &[f64], whh: &[f64], bih: &[f64], bhh: &[f64]) -> LstmLayer {
        let g = 4 * hidden;
        let cols = inp + hidden;
        let mut w = vec![0.0; g * cols];
        for r in 0..g {
            w[r * cols..r * cols + inp].copy_from_slice(&wih[r * inp..(r + 1) * inp]);
            w[r * cols + inp..(r + 1) * cols].copy_from_slice(&whh[r * hidden..(r + 1) * hidden]);
        }
        let b: Vec<f64> = bih.iter().zip(bhh).map(|(a, b)| a + b).collect();
        LstmLayer { inp, hidden, cell: Dense::from_rows(&w, &b, g, cols) }
    }
}

#[derive(Debug, Clone)]
pub struct Lstm {
    pub layers: Vec<LstmLayer>,
    pub c_in: usize,
    pub hidden: usize,
}

#[derive(Debug, Clone)]
pub enum Encoder {
    Tcn(Tcn),
    Lstm(Lstm),
}

impl Encoder {
    pub fn c_in(&self) -> usize {
        match self {
            Encoder::Tcn(t) => t.c_in,
            Encoder::Lstm(l) => l.c_in,
        }
    }
}

#[derive(Debug, Clone)]
struct BlockState {
    ring1: Vec<f64>,
    ring2: Vec<f64>,
    slots: usize,
    pos: usize,
    h1: Vec<f64>,
    y: Vec<f64>,
}

/// The encoder's running state for one stream (one trial, one leg). Allocated once.
#[derive(Debug, Clone)]
pub struct EncoderState {
    xn: Vec<f64>,
    blocks: Vec<BlockState>,
    lstm_h: Vec<Vec<f64>>,
    lstm_c: Vec<Vec<f64>>,
    xin: Vec<f64>,
    gates: Vec<f64>,
    /// Samples seen since the last reset.
    pub steps: usize,
}

impl EncoderState {
    /// Back to zero state (start of a new trial).
    pub fn reset(&mut self) {
        for b in &mut self.blocks {
            b.ring1.fill(0.0);
            b.ring2.fill(0.0);
            b.pos = 0;
        }
        for h in &mut self.lstm_h {
            h.fill(0.0);
        }
        for c in &mut self.lstm_c {
            c.fill(0.0);
        }
        self.steps = 0;
    }
}

/// y = b + Σ_taps W_t x[now − (k−1−t)d], reading the ring.
#[inline(always)]
fn conv_step<const FMA: bool>(taps: &[Dense], b: &[f64], ring: &[f64], slots: usize, pos: usize, dil: usize, cin: usize, y: &mut [f64]) {
    y.copy_from_slice(b);
    let k = taps.len();
    for (t, d) in taps.iter().enumerate() {
        let lag = (k - 1 - t) * dil;
        let slot = (pos + slots - lag) % slots;
        let x = &ring[slot * cin..(slot + 1) * cin];
        for (j, &xj) in x.iter().enumerate() {
            let w = d.col(j);
            for i in 0..y.len() {
                y[i] = madd::<FMA>(w[i], xj, y[i]);
            }
        }
    }
}

#[inline(always)]
fn step<const FMA: bool>(m: &Model, st: &mut EncoderState, z: &mut [f64]) {
    match m.encoder.as_ref().unwrap() {
        Encoder::Tcn(tcn) => {
            for (bi, blk) in tcn.blocks.iter().enumerate() {
                let (before, rest) = st.blocks.split_at_mut(bi);
                let s = &mut rest[0];
                let x: &[f64] = if bi == 0 { &st.xn } else { &before[bi - 1].y };
                let (cin, cout, slots, pos) = (blk.cin, blk.cout, s.slots, s.pos);
                s.ring1[pos * cin..(pos + 1) * cin].copy_from_slice(x);
                conv_step::<FMA>(&blk.conv1, &blk.b1, &s.ring1, slots, pos, blk.dil, cin, &mut s.h1);
                for v in s.h1.iter_mut() {
                    *v = v.max(0.0);
                }
                s.ring2[pos * cout..(pos + 1) * cout].copy_from_slice(&s.h1);
                conv_step::<FMA>(&blk.conv2, &blk.b2, &s.ring2, slots, pos, blk.dil, cout, &mut s.y);
                // y = relu(relu(conv2) + res(x))
                match &blk.res {
                    Some(r) => {
                        for i in 0..cout {
                            let mut acc = r.b[i];
                            for j in 0..cin {
                                acc = madd::<FMA>(r.wt[j * cout + i], x[j], acc);
                            }
                            s.y[i] = (s.y[i].max(0.0) + acc).max(0.0);
                        }
                    }
                    None => {
                        for i in 0..cout {
                            s.y[i] = (s.y[i].max(0.0) + x[i]).max(0.0);
                        }
                    }
                }
                s.pos = (pos + 1) % slots;
            }
            z.copy_from_slice(&st.blocks.last().unwrap().y);
        }
        Encoder::Lstm(lstm) => {
            let hdim = lstm.hidden;
            for (k, layer) in lstm.layers.iter().enumerate() {
                let inp = layer.inp;
                if k == 0 {
                    st.xin[..inp].copy_from_slice(&st.xn);
                } else {
                    let (prev, _) = st.lstm_h.split_at(k);
                    st.xin[..inp].copy_from_slice(&prev[k - 1]);
                }
                st.xin[inp..inp + hdim].copy_from_slice(&st.lstm_h[k]);
                let cell = &layer.cell;
                let gates = &mut st.gates[..4 * hdim];
                gates.copy_from_slice(&cell.b);
                for j in 0..inp + hdim {
                    let xj = st.xin[j];
                    let w = cell.col(j);
                    for i in 0..4 * hdim {
                        gates[i] = madd::<FMA>(w[i], xj, gates[i]);
                    }
                }
                let (h, c) = (&mut st.lstm_h[k], &mut st.lstm_c[k]);
                for i in 0..hdim {
                    let ig = sigmoid::<FMA>(gates[i]);
                    let fg = sigmoid::<FMA>(gates[hdim + i]);
                    let gg = tanh::<FMA>(gates[2 * hdim + i]);
                    let og = sigmoid::<FMA>(gates[3 * hdim + i]);
                    c[i] = fg * c[i] + ig * gg;
                    h[i] = og * tanh::<FMA>(c[i]);
                }
            }
            z.copy_from_slice(lstm_top(st));
        }
    }
}

fn lstm_top(st: &EncoderState) -> &[f64] {
    st.lstm_h.last().unwrap()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn step_fma(m: &Model, st: &mut EncoderState, z: &mut [f64]) {
    step::<true>(m, st, z)
}

impl Model {
    /// A fresh (zero) encoder state; allocates, so make it once per stream.
    pub fn encoder_state(&self) -> EncoderState {
        let mut st = EncoderState {
            xn: vec![0.0; self.context_dim()],
            blocks: vec![],
            lstm_h: vec![],
            lstm_c: vec![],
            xin: vec![],
            gates: vec![],
            steps: 0,
        };
        match &self.encoder {
            Some(Encoder::Tcn(t)) => {
                st.blocks = t
                    .blocks
                    .iter()
                    .map(|b| BlockState {
                        ring1: vec![0.0; b.slots() * b.cin],
                        ring2: vec![0.0; b.slots() * b.cout],
                        slots: b.slots(),
                        pos: 0,
                        h1: vec![0.0; b.cout],
                        y: vec![0.0; b.cout],
                    })
                    .collect();
            }
            Some(Encoder::Lstm(l)) => {
                st.lstm_h = vec![vec![0.0; l.hidden]; l.layers.len()];
                st.lstm_c = vec![vec![0.0; l.hidden]; l.layers.len()];
                st.xin = vec![0.0; l.c_in.max(l.hidden) + l.hidden];
                st.gates = vec![0.0; 4 * l.hidden];
            }
            None => {}
        }
        st
    }

    /// One raw context sample `x` (C channels, as `context_features` gives them; NaN allowed) in,
    /// z (z_dim) out. Normalises with the stored statistics; non-finite normalised inputs become 0.
    pub fn encode_step(&self, st: &mut EncoderState, x: &[f64], z: &mut [f64]) -> Result<()> {
        let norm = match (&self.encoder, &self.norm) {
            (Some(_), Some(norm)) => norm,
            _ => return Err(Error::Unsupported(format!("method {:?} has no context encoder", self.meta.method))),
        };
        let c = self.context_dim();
        if x.len() != c {
            return Err(Error::InputShape(format!("context sample has {} channels, expected {c}", x.len())));
        }
        if z.len() != self.dz {
            return Err(Error::InputShape(format!("z output has {} entries, expected {}", z.len(), self.dz)));
        }
        if st.xn.len() != c {
            return Err(Error::InputShape("encoder state was made for a different model".into()));
        }
        for i in 0..c {
            let v = (x[i] - norm.mean[i]) / norm.std[i];
            st.xn[i] = if v.is_finite() { v } else { 0.0 };
        }
        #[cfg(target_arch = "x86_64")]
        if self.fma {
            // SAFETY: AVX2 and FMA were detected at load.
            unsafe { step_fma(self, st, z) };
            st.steps += 1;
            return Ok(());
        }
        step::<false>(self, st, z);
        st.steps += 1;
        Ok(())
    }
}
