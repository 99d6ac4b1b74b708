//! A model in memory: its metadata, networks, encoder and extension terms (loaded by `loader.rs`),
//! and the streaming encoder's entry points.

use std::collections::HashMap;

use crate::encoder::{step_dispatch, Encoder, EncoderState};
use crate::error::{Error, Result};
use crate::ext::Ext;
use crate::mlp::Mlp;
pub use crate::loader::{DELAN_METHODS, FORMAT, FORMAT_VERSION};
pub use crate::simd::Simd;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointType {
    Revolute,
    Prismatic,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EncoderKind {
    None,
    Tcn,
    Lstm,
}

/// The metadata of a weight file, parsed.
#[derive(Debug, Clone)]
pub struct Meta {
    pub method: String,
    pub lim: bool,
    pub joint_names: Vec<String>,
    pub joint_types: Vec<JointType>,
    pub encoder: EncoderKind,
    pub z_dim: usize,
    pub context_channels: Vec<String>,
    pub softplus_offset: f64,
    pub v_scale: f64,
    pub lim_scale: f64,
    pub dt: f64,
    pub coulomb_eps: f64,
    /// Every metadata entry as written (provenance included).
    pub raw: HashMap<String, String>,
}

/// Input normalisation of the context features.
#[derive(Debug, Clone)]
pub struct Norm {
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
}

/// A loaded model: immutable after load, shared freely across threads (`Sync`).
#[derive(Debug, Clone)]
pub struct Model {
    pub meta: Meta,
    /// Number of joints.
    pub n: usize,
    /// Length of φ(q).
    pub dphi: usize,
    /// Context dimension (0 without encoder).
    pub dz: usize,
    pub(crate) net_l: Mlp,
    pub(crate) net_v: Mlp,
    pub(crate) net_lim: Option<Mlp>,
    /// L, V, LIM rounded to float32, for the float32 lane rollouts (`lane_rollout.rs`).
    pub(crate) nets_f32: [Option<Mlp<f32>>; 3],
    pub(crate) norm: Option<Norm>,
    pub(crate) encoder: Option<Encoder>,
    pub(crate) ext: Ext,
    /// Per joint: (column of φ, column of the second entry or usize::MAX for prismatic).
    pub(crate) phi_cols: Vec<(usize, usize)>,
    /// Code path, decided once at load from the CPU.
    pub(crate) simd: Simd,
}

impl Model {
    /// Number of raw context channels the encoder reads (0 without encoder).
    pub fn context_dim(&self) -> usize {
        match &self.encoder {
            Some(e) => e.c_in(),
            None => 0,
        }
    }

    /// Choose the code path: `Some(level)` forces it (clamped to what the CPU has), `None` the best
    /// available (see `simd.rs`: AVX-512 and AVX2 agree bit for bit, the portable path to rounding).
    pub fn set_simd(&mut self, level: Option<Simd>) {
        let best = crate::simd::detect();
        self.simd = match level {
            None => best,
            Some(l) => l.min(best),
        };
    }

    pub fn simd(&self) -> Simd {
        self.simd
    }

    /// A fresh (zero) encoder state; allocates, so make it once per stream.
    pub fn encoder_state(&self) -> EncoderState {
        match &self.encoder {
            Some(e) => e.state(),
            None => EncoderState::empty(0),
        }
    }

    /// One raw context sample `x` (C channels, as `context_features` gives them; NaN allowed) in,
    /// z (z_dim) out. Normalises with the stored statistics; non-finite normalised inputs become 0.
    pub fn encode_step(&self, st: &mut EncoderState, x: &[f64], z: &mut [f64]) -> Result<()> {
        let (enc, norm) = match (&self.encoder, &self.norm) {
            (Some(enc), Some(norm)) => (enc, norm),
            _ => return Err(Error::Unsupported(format!("method {:?} has no context encoder", self.meta.method))),
        };
        let c = self.context_dim();
        if x.len() != c {
            return Err(Error::InputShape(format!("context sample has {} channels, expected {c}", x.len())));
        }
        if z.len() != self.dz {
            return Err(Error::InputShape(format!("z output has {} entries, expected {}", z.len(), self.dz)));
        }
        let xn = st.input_mut();
        if xn.len() != c {
            return Err(Error::InputShape("encoder state was made for a different model".into()));
        }
        for i in 0..c {
            let v = (x[i] - norm.mean[i]) / norm.std[i];
            xn[i] = if v.is_finite() { v } else { 0.0 };
        }
        step_dispatch(self.simd, enc, st, z);
        st.steps += 1;
        Ok(())
    }
}
