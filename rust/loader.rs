//! Loading a weight file (DESIGN.md section 3): parse the safetensors bytes, validate, build a `Model`.
//!
//! Validation is strict — every tensor name, dtype and shape is checked against the metadata and
//! against each other, unknown tensors are rejected — and every failure is an `Err`, never a panic:
//! a controller must be able to refuse a bad file and keep running.

use std::collections::{HashMap, HashSet};

use safetensors::{Dtype, SafeTensors};

use crate::encoder::{Encoder, Lstm, LstmLayer, Tcn, TcnBlock};
use crate::error::{Error, Result};
use crate::ext::Ext;
use crate::mlp::{Dense, Mlp};
use crate::model::{EncoderKind, JointType, Meta, Model, Norm};

pub const FORMAT: &str = "exolan-weights";
pub const FORMAT_VERSION: &str = "1";
/// Methods whose physics this engine runs (the black-box heads have no H, c, g).
pub const DELAN_METHODS: [&str; 4] = ["delan", "exolan", "delan-tcn", "delan-lstm"];

fn meta_err(key: &str, msg: impl Into<String>) -> Error {
    Error::Metadata { key: key.to_string(), msg: msg.into() }
}

struct MetaReader<'a>(&'a HashMap<String, String>);

impl MetaReader<'_> {
    fn str(&self, key: &str) -> Result<&str> {
        self.0.get(key).map(|s| s.as_str()).ok_or_else(|| meta_err(key, "missing"))
    }
    fn f64(&self, key: &str) -> Result<f64> {
        let s = self.str(key)?;
        let v: f64 = s.trim().parse().map_err(|_| meta_err(key, format!("not a number: {s:?}")))?;
        if !v.is_finite() {
            return Err(meta_err(key, "not finite"));
        }
        Ok(v)
    }
    fn f64_or(&self, key: &str, default: f64) -> Result<f64> {
        if self.0.contains_key(key) {
            self.f64(key)
        } else {
            Ok(default)
        }
    }
    fn usize(&self, key: &str) -> Result<usize> {
        let s = self.str(key)?;
        s.trim().parse().map_err(|_| meta_err(key, format!("not a non-negative integer: {s:?}")))
    }
    fn list(&self, key: &str) -> Result<Vec<String>> {
        let s = self.str(key)?;
        serde_json::from_str::<Vec<String>>(s).map_err(|e| meta_err(key, format!("not a JSON list of strings: {e}")))
    }
    fn bool(&self, key: &str) -> Result<bool> {
        match self.str(key)?.trim() {
            "true" | "True" | "1" => Ok(true),
            "false" | "False" | "0" => Ok(false),
            s => Err(meta_err(key, format!("expected \"true\" or \"false\", got {s:?}"))),
        }
    }
}

/// Tensor access with checks; records which names were used so leftovers can be rejected.
struct Tensors<'a> {
    st: SafeTensors<'a>,
    used: HashSet<String>,
}

impl Tensors<'_> {
    fn has(&self, name: &str) -> bool {
        self.st.names().contains(&name)
    }
    fn shape_of(&self, name: &str) -> Result<Vec<usize>> {
        let t = self.st.tensor(name).map_err(|_| Error::MissingTensor(name.to_string()))?;
        Ok(t.shape().to_vec())
    }
    /// The tensor's values (row-major), checking dtype and shape and finiteness.
    fn get(&mut self, name: &str, shape: &[usize]) -> Result<Vec<f64>> {
        self.get_checked(name, shape, false)
    }
    /// As `get`; `allow_pos_inf` admits +inf (the neutral strap stiffness).
    fn get_checked(&mut self, name: &str, shape: &[usize], allow_pos_inf: bool) -> Result<Vec<f64>> {
        let t = self.st.tensor(name).map_err(|_| Error::MissingTensor(name.to_string()))?;
        if t.dtype() != Dtype::F64 {
            return Err(Error::Dtype { name: name.to_string(), dtype: format!("{:?}", t.dtype()) });
        }
        if t.shape() != shape {
            return Err(Error::Shape { name: name.to_string(), expected: shape.to_vec(), got: t.shape().to_vec() });
        }
        let count: usize = shape.iter().product();
        let data = t.data();
        if data.len() != count * 8 {
            return Err(Error::Format(format!("tensor '{name}' holds {} bytes, expected {}", data.len(), count * 8)));
        }
        let v: Vec<f64> = data.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap())).collect();
        if v.iter().any(|x| !(x.is_finite() || (allow_pos_inf && *x == f64::INFINITY))) {
            return Err(Error::NonFiniteWeight(name.to_string()));
        }
        self.used.insert(name.to_string());
        Ok(v)
    }
    fn dense(&mut self, prefix: &str, out: usize, inp: usize) -> Result<Dense> {
        let w = self.get(&format!("{prefix}.weight"), &[out, inp])?;
        let b = self.get(&format!("{prefix}.bias"), &[out])?;
        Ok(Dense::from_rows(&w, &b, out, inp))
    }
    /// `prefix.{0..}` Linear layers: discovers the count and hidden widths, checks the chain.
    fn mlp(&mut self, prefix: &str, d_in: usize, d_out: usize) -> Result<Mlp> {
        // layers = 1 + the largest index named `prefix.{i}.*`; a gap is a missing tensor
        let dotted = format!("{prefix}.");
        let mut count = 0;
        for name in self.st.names() {
            if let Some(rest) = name.strip_prefix(&dotted) {
                if let Some((idx, _)) = rest.split_once('.') {
                    if let Ok(i) = idx.parse::<usize>() {
                        if i >= 64 {
                            return Err(Error::Unsupported(format!("{prefix}: more than 64 layers")));
                        }
                        count = count.max(i + 1);
                    }
                }
            }
        }
        if count == 0 {
            return Err(Error::MissingTensor(format!("{prefix}.0.weight")));
        }
        for i in 0..count {
            for part in ["weight", "bias"] {
                let name = format!("{prefix}.{i}.{part}");
                if !self.has(&name) {
                    return Err(Error::MissingTensor(name));
                }
            }
        }
        let mut layers = Vec::with_capacity(count);
        let mut inp = d_in;
        for i in 0..count {
            let name = format!("{prefix}.{i}.weight");
            let shape = self.shape_of(&name)?;
            let out = if i + 1 == count {
                d_out
            } else {
                match shape.as_slice() {
                    [h, _] if *h > 0 => *h,
                    _ => return Err(Error::Shape { name, expected: vec![0, inp], got: shape }),
                }
            };
            layers.push(self.dense(&format!("{prefix}.{i}"), out, inp)?);
            inp = out;
        }
        Ok(Mlp { layers, z_part: None, phi_part: None, back: vec![] })
    }
}

impl Model {
    /// Read and validate a weight file.
    pub fn load(path: impl AsRef<std::path::Path>) -> Result<Model> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|e| Error::Io(format!("{}: {e}", path.display())))?;
        Model::from_bytes(&bytes)
    }

    /// Parse and validate weight-file bytes. Never panics on malformed input.
    pub fn from_bytes(bytes: &[u8]) -> Result<Model> {
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| Error::Format(format!("{e:?}")))?;
        let raw = header.metadata().clone().ok_or_else(|| Error::Version("no __metadata__ in file".into()))?;
        let st = SafeTensors::deserialize(bytes).map_err(|e| Error::Format(format!("{e:?}")))?;
        let meta = parse_meta(&raw)?;
        let n = meta.joint_types.len();
        let (dphi, phi_cols) = phi_layout(&meta.joint_types);
        let mut ts = Tensors { st, used: HashSet::new() };
        let norm = load_norm(&mut ts, &meta)?;
        let m = MetaReader(&raw);
        let encoder = match meta.encoder {
            EncoderKind::None => {
                if meta.z_dim != 0 {
                    return Err(meta_err("z_dim", format!("{} without an encoder (expected 0)", meta.z_dim)));
                }
                None
            }
            EncoderKind::Tcn => Some(load_tcn(&mut ts, &m, meta.context_channels.len(), meta.z_dim)?),
            EncoderKind::Lstm => Some(load_lstm(&mut ts, &m, meta.context_channels.len(), meta.z_dim)?),
        };
        let dz = meta.z_dim;
        let (net_l, net_v, net_lim) = load_nets(&mut ts, &m, n, dphi, dz, meta.lim)?;
        let ext = Ext::load(n, |name, shape, inf| if ts.has(name) { ts.get_checked(name, shape, inf).map(Some) } else { Ok(None) })?;
        // Leftover tensors: a misspelt name must not be silently ignored.
        let mut names: Vec<&str> = ts.st.names();
        names.sort();
        for name in names {
            if !ts.used.contains(name) {
                return Err(Error::UnexpectedTensor(name.to_string()));
            }
        }
        let nets_f32 = [Some(net_l.to_f32()), Some(net_v.to_f32()), net_lim.as_ref().map(Mlp::to_f32)];
        Ok(Model {
            meta,
            n,
            dphi,
            dz,
            net_l,
            net_v,
            net_lim,
            nets_f32,
            norm,
            encoder,
            ext,
            phi_cols,
            simd: crate::simd::detect(),
        })
    }
}

/// The metadata entries, checked.
fn parse_meta(raw: &HashMap<String, String>) -> Result<Meta> {
    let m = MetaReader(raw);
    match raw.get("format").map(|s| s.as_str()) {
        Some(FORMAT) => {}
        other => return Err(Error::Version(format!("format is {other:?}, expected {FORMAT:?}"))),
    }
    match raw.get("format_version").map(|s| s.as_str()) {
        Some(FORMAT_VERSION) => {}
        other => {
            return Err(Error::Version(format!(
                "format_version is {other:?}; this engine reads version {FORMAT_VERSION}"
            )))
        }
    }
    let method = m.str("method")?.to_string();
    if !DELAN_METHODS.contains(&method.as_str()) {
        return Err(Error::Unsupported(format!(
            "method {method:?}: the engine runs the DeLaN-based methods {DELAN_METHODS:?}"
        )));
    }
    let lim = m.bool("lim")?;
    let joint_names = m.list("joint_names")?;
    let joint_types = m
        .list("joint_types")?
        .iter()
        .map(|t| match t.as_str() {
            "revolute" => Ok(JointType::Revolute),
            "prismatic" => Ok(JointType::Prismatic),
            other => Err(meta_err("joint_types", format!("unknown joint type {other:?}"))),
        })
        .collect::<Result<Vec<_>>>()?;
    let n = joint_types.len();
    if n == 0 || n > 64 {
        return Err(meta_err("joint_types", format!("{n} joints (expected 1..=64)")));
    }
    if joint_names.len() != n {
        return Err(meta_err("joint_names", format!("{} names for {n} joint types", joint_names.len())));
    }
    if let Some(a) = m.0.get("activation") {
        if a != "tanh" {
            return Err(Error::Unsupported(format!("activation {a:?} (only tanh)")));
        }
    }
    let encoder_kind = match m.str("encoder")? {
        "none" => EncoderKind::None,
        "tcn" => EncoderKind::Tcn,
        "lstm" => EncoderKind::Lstm,
        other => return Err(meta_err("encoder", format!("unknown encoder {other:?}"))),
    };
    let z_dim = m.usize("z_dim")?;
    let context_channels = if raw.contains_key("context_channels") { m.list("context_channels")? } else { vec![] };
    let softplus_offset = m.f64("softplus_offset")?;
    let v_scale = m.f64("v_scale")?;
    let lim_scale = if lim { m.f64("lim_scale")? } else { m.f64_or("lim_scale", 1.0)? };
    let dt = m.f64_or("dt", 0.0)?;
    let coulomb_eps = m.f64_or("coulomb_eps", 0.01)?;
    if !(coulomb_eps > 0.0) {
        return Err(meta_err("coulomb_eps", "must be > 0"));
    }
    Ok(Meta {
        method,
        lim,
        joint_names,
        joint_types,
        encoder: encoder_kind,
        z_dim,
        context_channels,
        softplus_offset,
        v_scale,
        lim_scale,
        dt,
        coulomb_eps,
        raw: raw.clone(),
    })
}

/// Length of φ(q) and, per joint, its columns (cos, sin; or q and usize::MAX for prismatic).
fn phi_layout(joint_types: &[JointType]) -> (usize, Vec<(usize, usize)>) {
    let n = joint_types.len();
    // φ(q): all cos of revolute joints, then all sin, then prismatic q.
    let nrev = joint_types.iter().filter(|t| **t == JointType::Revolute).count();
    let dphi = 2 * nrev + (n - nrev);
    let mut phi_cols = Vec::with_capacity(n);
    let (mut r, mut p) = (0, 0);
    for t in joint_types {
        match t {
            JointType::Revolute => {
                phi_cols.push((r, nrev + r));
                r += 1;
            }
            JointType::Prismatic => {
                phi_cols.push((2 * nrev + p, usize::MAX));
                p += 1;
            }
        }
    }
    (dphi, phi_cols)
}

/// Input normalisation of the context features (required with an encoder).
fn load_norm(ts: &mut Tensors, meta: &Meta) -> Result<Option<Norm>> {
    let c = meta.context_channels.len();
    Ok(if meta.encoder != EncoderKind::None || ts.has("norm.ctx_mean") {
        if c == 0 {
            return Err(meta_err("context_channels", "an encoder needs at least one context channel"));
        }
        let mean = ts.get("norm.ctx_mean", &[c])?;
        let std = ts.get("norm.ctx_std", &[c])?;
        if std.iter().any(|s| !(*s > 0.0)) {
            return Err(Error::NonFiniteWeight("norm.ctx_std (must be > 0)".into()));
        }
        Some(Norm { mean, std })
    } else {
        None
    })
}

/// The causal TCN: `tcn_levels` blocks of dilation 2^i, `c` input channels, z_dim out.
fn load_tcn(ts: &mut Tensors, m: &MetaReader, c: usize, z_dim: usize) -> Result<Encoder> {
    let levels = m.usize("tcn_levels")?;
    let kernel = m.usize("tcn_kernel")?;
    if levels == 0 || levels > 16 || kernel == 0 || kernel > 8 {
        return Err(meta_err("tcn_levels", format!("levels {levels}, kernel {kernel} out of range")));
    }
    let mut blocks = Vec::with_capacity(levels);
    let mut cin = c;
    for i in 0..levels {
        let p = format!("encoder.tcn.{i}");
        let s1 = ts.shape_of(&format!("{p}.conv1.weight"))?;
        let cout = match s1.as_slice() {
            [co, _, _] if *co > 0 => *co,
            _ => {
                return Err(Error::Shape {
                    name: format!("{p}.conv1.weight"),
                    expected: vec![0, cin, kernel],
                    got: s1,
                })
            }
        };
        let w1 = ts.get(&format!("{p}.conv1.weight"), &[cout, cin, kernel])?;
        let b1 = ts.get(&format!("{p}.conv1.bias"), &[cout])?;
        let w2 = ts.get(&format!("{p}.conv2.weight"), &[cout, cout, kernel])?;
        let b2 = ts.get(&format!("{p}.conv2.bias"), &[cout])?;
        let res = if cin != cout || ts.has(&format!("{p}.res.weight")) {
            let w = ts.get(&format!("{p}.res.weight"), &[cout, cin, 1])?;
            let b = ts.get(&format!("{p}.res.bias"), &[cout])?;
            Some(Dense::from_rows(&w, &b, cout, cin))
        } else {
            None
        };
        blocks.push(TcnBlock::new(1usize << i, kernel, cin, cout, &w1, &b1, &w2, &b2, res));
        cin = cout;
    }
    if cin != z_dim {
        return Err(meta_err("z_dim", format!("{z_dim}, but the TCN's last block has {cin} channels")));
    }
    Ok(Encoder::Tcn(Tcn { blocks, c_in: c }))
}

/// The LSTM: `lstm_layers` layers of hidden size z_dim.
fn load_lstm(ts: &mut Tensors, m: &MetaReader, c: usize, z_dim: usize) -> Result<Encoder> {
    let layers_n = m.usize("lstm_layers")?;
    if layers_n == 0 || layers_n > 64 {
        return Err(meta_err("lstm_layers", format!("{layers_n} out of range")));
    }
    let s0 = ts.shape_of("encoder.lstm.weight_ih_l0")?;
    let hidden = match s0.as_slice() {
        [g, _] if *g > 0 && g % 4 == 0 => g / 4,
        _ => {
            return Err(Error::Shape {
                name: "encoder.lstm.weight_ih_l0".into(),
                expected: vec![4 * z_dim, c],
                got: s0,
            })
        }
    };
    let mut layers = Vec::with_capacity(layers_n);
    let mut inp = c;
    for k in 0..layers_n {
        let wih = ts.get(&format!("encoder.lstm.weight_ih_l{k}"), &[4 * hidden, inp])?;
        let whh = ts.get(&format!("encoder.lstm.weight_hh_l{k}"), &[4 * hidden, hidden])?;
        let bih = ts.get(&format!("encoder.lstm.bias_ih_l{k}"), &[4 * hidden])?;
        let bhh = ts.get(&format!("encoder.lstm.bias_hh_l{k}"), &[4 * hidden])?;
        layers.push(LstmLayer::new(inp, hidden, &wih, &whh, &bih, &bhh));
        inp = hidden;
    }
    if hidden != z_dim {
        return Err(meta_err("z_dim", format!("{z_dim}, but the LSTM's hidden size is {hidden}")));
    }
    Ok(Encoder::Lstm(Lstm { layers, c_in: c, hidden }))
}

type Nets = (Mlp, Mlp, Option<Mlp>);

/// The L, V and LIM networks on [φ; z], with their declared widths checked.
fn load_nets(ts: &mut Tensors, m: &MetaReader, n: usize, dphi: usize, dz: usize, lim: bool) -> Result<Nets> {
    let raw = m.0;
    let d_in = dphi + dz;
    let net_l = ts.mlp("delan.L", d_in, n * (n + 1) / 2)?.with_z_part(dphi);
    // V with its transposed layers: the lane rollouts take g = ∂V/∂q from one reverse pass
    let net_v = ts.mlp("delan.V", d_in, 1)?.with_z_part(dphi).with_backward(dphi);
    let net_lim = if lim { Some(ts.mlp("lim", d_in, n)?.with_z_part(dphi)) } else { None };
    for (key, net) in [("hidden", Some(&net_l)), ("lim_hidden", net_lim.as_ref())] {
        if let (Some(net), true) = (net, raw.contains_key(key)) {
            let h = m.usize(key)?;
            if net.layers.len() > 1 && net.layers[0].out != h {
                return Err(meta_err(key, format!("{h}, but the tensors have width {}", net.layers[0].out)));
            }
        }
    }
    Ok((net_l, net_v, net_lim))
}
