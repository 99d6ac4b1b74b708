//! Random-weight model files in the exact export format, for tests, benchmarks and the example
//! when no trained model is at hand. Weights follow torch's default Linear/Conv init range
//! (uniform ±1/√fan_in), drawn from a seeded SplitMix64 so files are reproducible.

use std::collections::HashMap;

use safetensors::tensor::{Dtype, TensorView};

use crate::{Inputs, LaneWorkspace, Model, Pool, Result, Workspace, ZSeq};

/// What to generate.
#[derive(Debug, Clone)]
pub struct SynthConfig {
    pub joint_types: Vec<&'static str>,
    /// "none", "tcn" or "lstm".
    pub encoder: &'static str,
    pub lim: bool,
    pub hidden: usize,
    pub lim_hidden: usize,
    pub z_dim: usize,
    pub context_channels: usize,
    pub tcn_levels: usize,
    pub lstm_layers: usize,
    pub seed: u64,
    /// Extra tensors (e.g. `ext.damping`) with their shapes and values; a name that the
    /// generator also makes replaces the generated tensor.
    pub extra: Vec<(String, Vec<usize>, Vec<f64>)>,
    /// Metadata entries to override or add.
    pub meta: Vec<(String, String)>,
}

impl Default for SynthConfig {
    /// The paper's ExoLaN: hip + knee, TCN (5 levels, 16 channels), DeLaN 64, LIM 16.
    fn default() -> Self {
        SynthConfig {
            joint_types: vec!["revolute", "revolute"],
            encoder: "tcn",
            lim: true,
            hidden: 64,
            lim_hidden: 16,
            z_dim: 16,
            context_channels: 7,
            tcn_levels: 5,
            lstm_layers: 5,
            seed: 1,
            extra: vec![],
            meta: vec![],
        }
    }
}

/// splitmix64: the synthetic models' weights, and the kernels' tests' inputs.
pub(crate) struct Rng(pub(crate) u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
    pub(crate) fn uniform(&mut self, count: usize, bound: f64) -> Vec<f64> {
        (0..count).map(|_| (2.0 * self.next() - 1.0) * bound).collect()
    }
}

/// The model shapes every code path is tested on: TCN, LSTM and no encoder, with and without LIM, 1 and 3
/// joints with a prismatic one (the general-n solve and φ layout).
pub fn shapes() -> Vec<SynthConfig> {
    let d = SynthConfig::default();
    vec![
        d.clone(),
        SynthConfig { lim: false, seed: 2, ..d.clone() },
        SynthConfig { encoder: "lstm", seed: 3, ..d.clone() },
        SynthConfig { encoder: "none", seed: 4, ..d.clone() },
        SynthConfig { joint_types: vec!["revolute", "prismatic", "revolute"], seed: 5, ..d.clone() },
        SynthConfig { joint_types: vec!["prismatic"], encoder: "none", seed: 6, ..d },
    ]
}

/// `count` deterministic pseudo-random values uniform in (−scale, scale): inputs for tests and benchmarks.
pub fn pseudo(seed: u64, count: usize, scale: f64) -> Vec<f64> {
    Rng(seed).uniform(count, scale)
}

/// Serialised safetensors bytes of a random model following DESIGN.md section 3.
pub fn random_weights(cfg: &SynthConfig) -> Vec<u8> {
    let mut rng = Rng(cfg.seed);
    let n = cfg.joint_types.len();
    let nrev = cfg.joint_types.iter().filter(|t| **t == "revolute").count();
    let dz = if cfg.encoder == "none" { 0 } else { cfg.z_dim };
    let d_in = 2 * nrev + (n - nrev) + dz;
    let c = cfg.context_channels;
    let mut t: Vec<(String, Vec<usize>, Vec<f64>)> = vec![];
    let lin = |t: &mut Vec<(String, Vec<usize>, Vec<f64>)>, rng: &mut Rng, name: String, out: usize, inp: usize| {
        let bound = 1.0 / (inp as f64).sqrt();
        t.push((format!("{name}.weight"), vec![out, inp], rng.uniform(out * inp, bound)));
        t.push((format!("{name}.bias"), vec![out], rng.uniform(out, bound)));
    };
    for (net, out) in [("delan.L", n * (n + 1) / 2), ("delan.V", 1)] {
        lin(&mut t, &mut rng, format!("{net}.0"), cfg.hidden, d_in);
        lin(&mut t, &mut rng, format!("{net}.1"), cfg.hidden, cfg.hidden);
        lin(&mut t, &mut rng, format!("{net}.2"), out, cfg.hidden);
    }
    if cfg.lim {
        lin(&mut t, &mut rng, "lim.0".into(), cfg.lim_hidden, d_in);
        lin(&mut t, &mut rng, "lim.1".into(), cfg.lim_hidden, cfg.lim_hidden);
        lin(&mut t, &mut rng, "lim.2".into(), n, cfg.lim_hidden);
    }
    if cfg.encoder != "none" {
        t.push(("norm.ctx_mean".into(), vec![c], rng.uniform(c, 0.5)));
        t.push(("norm.ctx_std".into(), vec![c], rng.uniform(c, 0.4).iter().map(|v| 1.0 + v).collect()));
    }
    if cfg.encoder == "tcn" {
        let mut cin = c;
        for i in 0..cfg.tcn_levels {
            let co = cfg.z_dim;
            let b1 = 1.0 / ((cin * 2) as f64).sqrt();
            t.push((format!("encoder.tcn.{i}.conv1.weight"), vec![co, cin, 2], rng.uniform(co * cin * 2, b1)));
            t.push((format!("encoder.tcn.{i}.conv1.bias"), vec![co], rng.uniform(co, b1)));
            let b2 = 1.0 / ((co * 2) as f64).sqrt();
            t.push((format!("encoder.tcn.{i}.conv2.weight"), vec![co, co, 2], rng.uniform(co * co * 2, b2)));
            t.push((format!("encoder.tcn.{i}.conv2.bias"), vec![co], rng.uniform(co, b2)));
            if cin != co {
                let br = 1.0 / (cin as f64).sqrt();
                t.push((format!("encoder.tcn.{i}.res.weight"), vec![co, cin, 1], rng.uniform(co * cin, br)));
                t.push((format!("encoder.tcn.{i}.res.bias"), vec![co], rng.uniform(co, br)));
            }
            cin = co;
        }
    }
    if cfg.encoder == "lstm" {
        let h = cfg.z_dim;
        let bound = 1.0 / (h as f64).sqrt();
        let mut inp = c;
        for k in 0..cfg.lstm_layers {
            t.push((format!("encoder.lstm.weight_ih_l{k}"), vec![4 * h, inp], rng.uniform(4 * h * inp, bound)));
            t.push((format!("encoder.lstm.weight_hh_l{k}"), vec![4 * h, h], rng.uniform(4 * h * h, bound)));
            t.push((format!("encoder.lstm.bias_ih_l{k}"), vec![4 * h], rng.uniform(4 * h, bound)));
            t.push((format!("encoder.lstm.bias_hh_l{k}"), vec![4 * h], rng.uniform(4 * h, bound)));
            inp = h;
        }
    }
    for e in &cfg.extra {
        t.retain(|x| x.0 != e.0);
        t.push(e.clone());
    }

    let jt: Vec<String> = cfg.joint_types.iter().map(|s| s.to_string()).collect();
    let names: Vec<String> = (0..n).map(|i| format!("j{i}")).collect();
    let chans: Vec<String> = (0..if cfg.encoder == "none" { 0 } else { c }).map(|i| format!("x{i}")).collect();
    let method = match cfg.encoder {
        "tcn" => "exolan",
        "lstm" => "delan-lstm",
        _ => "delan",
    };
    let mut meta: HashMap<String, String> = [
        ("format", "exolan-weights".to_string()),
        ("format_version", "1".to_string()),
        ("method", method.to_string()),
        ("lim", cfg.lim.to_string()),
        ("joint_names", serde_json::to_string(&names).unwrap()),
        ("joint_types", serde_json::to_string(&jt).unwrap()),
        ("encoder", cfg.encoder.to_string()),
        ("z_dim", dz.to_string()),
        ("context_channels", serde_json::to_string(&chans).unwrap()),
        ("tcn_levels", cfg.tcn_levels.to_string()),
        ("tcn_kernel", "2".to_string()),
        ("lstm_layers", cfg.lstm_layers.to_string()),
        ("hidden", cfg.hidden.to_string()),
        ("lim_hidden", cfg.lim_hidden.to_string()),
        ("activation", "tanh".to_string()),
        ("softplus_offset", "0.001".to_string()),
        ("v_scale", "5.0".to_string()),
        ("lim_scale", "0.1".to_string()),
        ("dt", "0.005".to_string()),
        ("coulomb_eps", "0.01".to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    for (k, v) in &cfg.meta {
        meta.insert(k.clone(), v.clone());
    }

    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = t
        .into_iter()
        .map(|(name, shape, v)| (name, shape, v.iter().flat_map(|x| x.to_le_bytes()).collect()))
        .collect();
    let views: Vec<(String, TensorView)> = bytes
        .iter()
        .map(|(name, shape, b)| (name.clone(), TensorView::new(Dtype::F64, shape.clone(), b).unwrap()))
        .collect();
    canonical(safetensors::serialize(views, Some(meta)).unwrap())
}

/// The same file with its JSON header's keys in sorted order. `safetensors::serialize` takes the metadata
/// as a `HashMap`, whose iteration order changes from process to process; sorted, the same config gives
/// the same bytes in every run (a fuzz test's mutation `i` is then the same file each time). Tensor offsets
/// are relative to the data section, so only the header changes; it is padded with spaces to a multiple of
/// 8 bytes, as safetensors writes it.
fn canonical(file: Vec<u8>) -> Vec<u8> {
    let hl = u64::from_le_bytes(file[..8].try_into().unwrap()) as usize;
    // serde_json's default map is ordered by key
    let header: serde_json::Value = serde_json::from_slice(&file[8..8 + hl]).unwrap();
    let mut h = serde_json::to_vec(&header).unwrap();
    while !h.len().is_multiple_of(8) {
        h.push(b' ');
    }
    let mut out = Vec::with_capacity(8 + h.len() + file.len() - 8 - hl);
    out.extend_from_slice(&(h.len() as u64).to_le_bytes());
    out.extend_from_slice(&h);
    out.extend_from_slice(&file[8 + hl..]);
    out
}

/// The batched-rollout set-up of the benchmarks and profilers: B rollouts of T steps from q0 = q̇0 with
/// per-step z (smooth deterministic inputs), one workspace per element (and the float32 path's lane
/// workspaces), the outputs.
#[derive(Debug)]
pub struct BatchSetup {
    pub q0: Vec<f64>,
    pub tau: Vec<f64>,
    pub z: Vec<f64>,
    pub f_v: Vec<f64>,
    pub wss: Vec<Workspace>,
    pub lws: Vec<LaneWorkspace>,
    pub q: Vec<f64>,
    pub qd: Vec<f64>,
}

impl BatchSetup {
    pub fn new(m: &Model, bsz: usize, t_len: usize) -> BatchSetup {
        let (n, dz) = (m.n, m.dz);
        BatchSetup {
            q0: (0..bsz * n).map(|i| (i as f64 * 0.1).sin()).collect(),
            tau: (0..bsz * t_len * n).map(|i| (i as f64 * 0.07).sin() * 5.0).collect(),
            z: (0..bsz * t_len * dz).map(|i| (i as f64 * 0.013).sin()).collect(),
            f_v: (0..bsz * t_len).map(|i| 200.0 + (i as f64).sin()).collect(),
            wss: (0..bsz).map(|_| m.workspace()).collect(),
            lws: m.lane_workspaces(bsz),
            q: vec![0.0; bsz * (t_len + 1) * n],
            qd: vec![0.0; bsz * (t_len + 1) * n],
        }
    }

    /// One `rollout_batch` (dt 0.005) on `pool`.
    pub fn run(&mut self, m: &Model, pool: &Pool) -> Result<()> {
        let inp = Inputs { tau: &self.tau, z: ZSeq::PerStep(&self.z), f_v: Some(&self.f_v), tau_e: None };
        m.rollout_batch(pool, &mut self.wss, &self.q0, &self.q0, inp, 0.005, &mut self.q, &mut self.qd)
    }

    /// The same batch in float32 (`rollout_batch_f32`).
    pub fn run_f32(&mut self, m: &Model, pool: &Pool) -> Result<()> {
        let inp = Inputs { tau: &self.tau, z: ZSeq::PerStep(&self.z), f_v: Some(&self.f_v), tau_e: None };
        m.rollout_batch_f32(pool, &mut self.lws, &self.q0, &self.q0, inp, 0.005, &mut self.q, &mut self.qd)
    }
}
