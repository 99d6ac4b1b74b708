//! Streaming context encoders: one raw sample in, z out (DESIGN.md section 2, "Encoders").
//!
//! Causal TCN: each conv of dilation d and kernel k needs its input at t, t−d, …, t−(k−1)d, kept in
//! a ring buffer of (k−1)·d + 1 slots per conv; zero-initialised rings are exactly torch's left zero
//! padding. LSTM: the (h, c) state per layer. Both start from zero state, as a trial does in torch.

use crate::error::Error;
use crate::math::{sigmoid_slice, tanh_slice};
use crate::mlp::{dense, Dense};
use crate::simd::simd_dispatch;

#[derive(Debug, Clone)]
pub struct TcnBlock {
    pub dil: usize,
    pub kernel: usize,
    pub cin: usize,
    pub cout: usize,
    /// The dilated conv as one dense map over the stacked taps [x(t−(k−1)d); …; x(t)]
    /// (torch's tap t multiplies x[t_now − (k−1−t)·d]).
    conv1: Dense,
    conv2: Dense,
    res: Option<Dense>,
}

/// torch (cout, cin, k) conv weight -> dense (cout, k·cin) with tap-major columns.
fn stacked(w: &[f64], b: &[f64], cout: usize, cin: usize, k: usize) -> Dense {
    let mut rows = vec![0.0; cout * k * cin];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..k {
                rows[o * k * cin + t * cin + i] = w[(o * cin + i) * k + t];
            }
        }
    }
    Dense::from_rows(&rows, b, cout, k * cin)
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
            conv1: stacked(w1, b1, cout, cin, kernel),
            conv2: stacked(w2, b2, cout, cout, kernel),
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

    /// A fresh (zero) state for one stream; allocates.
    pub(crate) fn state(&self) -> EncoderState {
        let mut st = EncoderState::empty(self.c_in());
        match self {
            Encoder::Tcn(t) => {
                st.blocks = t
                    .blocks
                    .iter()
                    .map(|b| BlockState {
                        ring1: vec![0.0; b.slots() * b.cin],
                        ring2: vec![0.0; b.slots() * b.cout],
                        slots: b.slots(),
                        pos: 0,
                        stack: vec![0.0; b.kernel * b.cin.max(b.cout)],
                        h1: vec![0.0; b.cout],
                        r: vec![0.0; b.cout],
                        y: vec![0.0; b.cout],
                    })
                    .collect();
            }
            Encoder::Lstm(l) => {
                st.lstm_h = vec![vec![0.0; l.hidden]; l.layers.len()];
                st.lstm_c = vec![vec![0.0; l.hidden]; l.layers.len()];
                st.xin = vec![0.0; l.c_in.max(l.hidden) + l.hidden];
                st.gates = vec![0.0; 4 * l.hidden];
                st.tanh_c = vec![0.0; l.hidden];
            }
        }
        st
    }
}

#[derive(Debug, Clone)]
struct BlockState {
    ring1: Vec<f64>,
    ring2: Vec<f64>,
    slots: usize,
    pos: usize,
    stack: Vec<f64>,
    h1: Vec<f64>,
    r: Vec<f64>,
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
    tanh_c: Vec<f64>,
    /// Samples seen since the last reset.
    pub steps: usize,
    /// Outcome of the last batched task run on this state.
    pub(crate) status: Option<Error>,
}

impl EncoderState {
    /// The state of a model without encoder (and the start of every other).
    pub(crate) fn empty(c: usize) -> EncoderState {
        EncoderState {
            xn: vec![0.0; c],
            blocks: vec![],
            lstm_h: vec![],
            lstm_c: vec![],
            xin: vec![],
            gates: vec![],
            tanh_c: vec![],
            steps: 0,
            status: None,
        }
    }

    /// The normalised input of the next step (C values).
    pub(crate) fn input_mut(&mut self) -> &mut [f64] {
        &mut self.xn
    }

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

/// Gather the taps x[now − (k−1−t)d], t = 0..k, from the ring into one contiguous vector.
#[inline(always)]
fn gather(ring: &[f64], slots: usize, pos: usize, dil: usize, k: usize, c: usize, stack: &mut [f64]) {
    for t in 0..k {
        let lag = (k - 1 - t) * dil;
        let slot = (pos + slots - lag) % slots;
        stack[t * c..(t + 1) * c].copy_from_slice(&ring[slot * c..(slot + 1) * c]);
    }
}

/// One step from the normalised input in `st` (see `EncoderState::input_mut`) to z.
#[inline(always)]
fn step<const FMA: bool, const WIDE: bool>(enc: &Encoder, st: &mut EncoderState, z: &mut [f64]) {
    match enc {
        Encoder::Tcn(tcn) => {
            for (bi, blk) in tcn.blocks.iter().enumerate() {
                let (before, rest) = st.blocks.split_at_mut(bi);
                let s = &mut rest[0];
                let x: &[f64] = if bi == 0 { &st.xn } else { &before[bi - 1].y };
                let (cin, cout, slots, pos, k) = (blk.cin, blk.cout, s.slots, s.pos, blk.kernel);
                s.ring1[pos * cin..(pos + 1) * cin].copy_from_slice(x);
                gather(&s.ring1, slots, pos, blk.dil, k, cin, &mut s.stack);
                dense::<f64, FMA, WIDE>(&blk.conv1, 1, &s.stack, &mut s.h1);
                for v in s.h1.iter_mut() {
                    *v = v.max(0.0);
                }
                s.ring2[pos * cout..(pos + 1) * cout].copy_from_slice(&s.h1);
                gather(&s.ring2, slots, pos, blk.dil, k, cout, &mut s.stack);
                dense::<f64, FMA, WIDE>(&blk.conv2, 1, &s.stack, &mut s.y);
                // y = relu(relu(conv2) + res(x))
                let r: &[f64] = match &blk.res {
                    Some(res) => {
                        dense::<f64, FMA, WIDE>(res, 1, x, &mut s.r);
                        &s.r
                    }
                    None => x,
                };
                for (yi, ri) in s.y.iter_mut().zip(r) {
                    *yi = (yi.max(0.0) + ri).max(0.0);
                }
                s.pos = (pos + 1) % slots;
            }
            z.copy_from_slice(&st.blocks.last().unwrap().y);
        }
        Encoder::Lstm(lstm) => {
            let hd = lstm.hidden;
            for (k, layer) in lstm.layers.iter().enumerate() {
                let inp = layer.inp;
                if k == 0 {
                    st.xin[..inp].copy_from_slice(&st.xn);
                } else {
                    st.xin[..inp].copy_from_slice(&st.lstm_h[k - 1]);
                }
                st.xin[inp..inp + hd].copy_from_slice(&st.lstm_h[k]);
                let gates = &mut st.gates[..4 * hd];
                dense::<f64, FMA, WIDE>(&layer.cell, 1, &st.xin[..inp + hd], gates);
                // gate order i, f, g, o
                let (ifg, rest) = gates.split_at_mut(2 * hd);
                let (g, o) = rest.split_at_mut(hd);
                sigmoid_slice::<FMA>(ifg);
                tanh_slice::<FMA>(g);
                sigmoid_slice::<FMA>(o);
                let (ig, fg) = ifg.split_at(hd);
                let c = &mut st.lstm_c[k];
                let tc = &mut st.tanh_c[..hd];
                for i in 0..hd {
                    c[i] = fg[i] * c[i] + ig[i] * g[i];
                    tc[i] = c[i];
                }
                tanh_slice::<FMA>(tc);
                let h = &mut st.lstm_h[k];
                for i in 0..hd {
                    h[i] = o[i] * tc[i];
                }
            }
            z.copy_from_slice(lstm_top(st));
        }
    }
}

fn lstm_top(st: &EncoderState) -> &[f64] {
    st.lstm_h.last().unwrap()
}

simd_dispatch!(pub(crate) fn step_dispatch(enc: &Encoder, st: &mut EncoderState, z: &mut [f64]) = step;);
