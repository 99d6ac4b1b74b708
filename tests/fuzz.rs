//! Fuzz-style robustness of the loader: thousands of mutated, truncated and spliced weight files.
//! Each must give `Ok` or `Err` — never a panic (a controller must survive a bad file).

use std::panic::{catch_unwind, AssertUnwindSafe};

use exolan::synth::{random_weights, SynthConfig};
use exolan::{Error, Model};

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn header_len(b: &[u8]) -> usize {
    if b.len() < 8 {
        return 0;
    }
    u64::from_le_bytes(b[..8].try_into().unwrap()) as usize
}

/// One random mutation, biased towards the header (8-byte length + JSON), where the structure is.
fn mutate(rng: &mut Rng, src: &[u8]) -> Vec<u8> {
    let mut b = src.to_vec();
    let hl = (8 + header_len(src)).min(b.len());
    let pos = |rng: &mut Rng, len: usize| if rng.below(4) > 0 { rng.below(hl.min(len)) } else { rng.below(len) };
    for _ in 0..1 + rng.below(4) {
        if b.is_empty() {
            break;
        }
        match rng.below(9) {
            0 => {
                let p = pos(rng, b.len());
                b[p] ^= 1 << rng.below(8);
            }
            1 => {
                let p = pos(rng, b.len());
                b[p] = rng.next() as u8;
            }
            2 => b.truncate(rng.below(b.len())),
            3 => {
                let p = pos(rng, b.len());
                b.remove(p);
            }
            4 => {
                let p = pos(rng, b.len());
                b.insert(p, b"{}[],:\"0123456789-.eE"[rng.below(21)]);
            }
            5 if b.len() >= 8 => {
                // header length field: off by a little or wildly
                let v = header_len(&b) as i64 + [1i64, -1, 8, -8, 1 << 40, -(1 << 20)][rng.below(6)];
                b[..8].copy_from_slice(&(v as u64).to_le_bytes());
            }
            6 => {
                // replace a digit in the header JSON (shapes, offsets)
                let digits: Vec<usize> = (8..hl.min(b.len())).filter(|&i| b[i].is_ascii_digit()).collect();
                if !digits.is_empty() {
                    let i = digits[rng.below(digits.len())];
                    b[i] = b"0123456789"[rng.below(10)];
                }
            }
            7 => {
                // duplicate a chunk (splice)
                let a = pos(rng, b.len());
                let l = rng.below(64).min(b.len() - a);
                let chunk = b[a..a + l].to_vec();
                let at = rng.below(b.len());
                b.splice(at..at, chunk);
            }
            _ => {
                // swap a dtype / key word
                // searched in the raw bytes: earlier mutations may have left invalid UTF-8 in the header, where
                // a lossy string's offsets are not byte offsets
                let (from, to) = [("F64", "F32"), ("F64", "I64"), ("delan.L", "delan.X"), ("\"1\"", "\"2\""), ("tcn", "lstm"),
                    ("true", "false"), ("revolute", "prismatic"), ("weight", "wieght"), ("0.001", "nan")][rng.below(9)];
                let (from, to) = (from.as_bytes(), to.as_bytes());
                let (lo, hi) = (8.min(b.len()), hl.min(b.len()));
                if let Some(i) = b[lo..hi].windows(from.len()).position(|w| w == from) {
                    if from.len() == to.len() {
                        b[lo + i..lo + i + from.len()].copy_from_slice(to);
                    }
                }
            }
        }
    }
    b
}

fn load_no_panic(bytes: &[u8], what: &str) -> Result<Model, Error> {
    match catch_unwind(AssertUnwindSafe(|| Model::from_bytes(bytes))) {
        Ok(r) => r,
        Err(_) => panic!("the loader panicked on {what} ({} bytes)", bytes.len()),
    }
}

#[test]
fn synthetic_files_are_byte_reproducible() {
    // the fuzz cases below are numbered: mutation i must be the same file in every run
    let cfg = SynthConfig { hidden: 8, lim_hidden: 4, z_dim: 4, tcn_levels: 2, ..Default::default() };
    let a = random_weights(&cfg);
    for _ in 0..5 {
        assert_eq!(random_weights(&cfg), a);
    }
    assert!(Model::from_bytes(&a).is_ok());
}

#[test]
fn mutated_files_never_panic() {
    let sources = [
        random_weights(&SynthConfig { hidden: 8, lim_hidden: 4, z_dim: 4, tcn_levels: 2, ..Default::default() }),
        random_weights(&SynthConfig { encoder: "lstm", hidden: 8, lim_hidden: 4, z_dim: 4, lstm_layers: 2, ..Default::default() }),
        random_weights(&SynthConfig { encoder: "none", lim: false, hidden: 8, ..Default::default() }),
    ];
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let (mut ok, mut err) = (0, 0);
    for i in 0..30000 {
        let src = &sources[i % sources.len()];
        let b = mutate(&mut rng, src);
        match load_no_panic(&b, &format!("mutation {i}")) {
            Ok(m) => {
                // a file that loads must also evaluate without panicking
                ok += 1;
                let mut ws = m.workspace();
                let _ = ws.set_z(&m, &vec![0.1; m.dz]);
                let mut out = vec![0.0; m.n];
                let q = vec![0.3; m.n];
                let _ = m.inverse_dynamics(&mut ws, &q, &q, &q, 10.0, None, &mut out);
                let _ = m.forward_dynamics(&mut ws, &q, &q, &q, 10.0, None, &mut out);
                if m.dz > 0 {
                    let mut st = m.encoder_state();
                    let mut z = vec![0.0; m.dz];
                    let _ = m.encode_step(&mut st, &vec![0.5; m.context_dim()], &mut z);
                }
            }
            Err(e) => {
                err += 1;
                assert!(!e.to_string().is_empty());
            }
        }
    }
    // the mutations must actually break files (and some survive): otherwise this proves nothing
    assert!(err > 15000, "only {err} of 30000 mutated files were rejected");
    assert!(ok > 10, "only {ok} mutated files loaded");
}

#[test]
fn every_truncation_is_an_error() {
    let src = random_weights(&SynthConfig { hidden: 8, lim_hidden: 4, z_dim: 4, tcn_levels: 2, ..Default::default() });
    let hl = 8 + header_len(&src);
    // every prefix through the header, then a stride through the data
    let cuts: Vec<usize> = (0..hl + 16).chain((hl + 16..src.len()).step_by(7)).collect();
    for cut in cuts {
        let r = load_no_panic(&src[..cut], &format!("truncation at {cut}"));
        assert!(r.is_err(), "a file truncated to {cut} of {} bytes loaded", src.len());
    }
    assert!(Model::from_bytes(&src).is_ok());
}

#[test]
fn validation_errors_name_the_problem() {
    let cfg = SynthConfig::default();
    let cases: Vec<(SynthConfig, &str)> = vec![
        (SynthConfig { meta: vec![("format_version".into(), "2".into())], ..cfg.clone() }, "format_version"),
        (SynthConfig { meta: vec![("format".into(), "other".into())], ..cfg.clone() }, "format"),
        (SynthConfig { meta: vec![("method".into(), "mlp-tcn".into())], ..cfg.clone() }, "unsupported model"),
        (SynthConfig { meta: vec![("joint_types".into(), "[\"revolute\",\"hinge\"]".into())], ..cfg.clone() }, "hinge"),
        (SynthConfig { meta: vec![("z_dim".into(), "12".into())], ..cfg.clone() }, "z_dim"),
        (SynthConfig { meta: vec![("v_scale".into(), "abc".into())], ..cfg.clone() }, "v_scale"),
        (
            SynthConfig { extra: vec![("delan.V.1.weight".into(), vec![64, 63], vec![0.0; 64 * 63])], ..cfg.clone() },
            "delan.V.1.weight",
        ),
        (SynthConfig { extra: vec![("delan.L.2.bias".into(), vec![3], vec![0.0, f64::NAN, 0.0])], ..cfg.clone() }, "NaN"),
        (SynthConfig { extra: vec![("encoder.tcn.9.conv1.weight".into(), vec![1], vec![0.0])], ..cfg.clone() }, "unexpected tensor"),
        (SynthConfig { extra: vec![("ext.coulomb".into(), vec![2], vec![-1.0, 0.0])], ..cfg.clone() }, "ext.coulomb"),
        (SynthConfig { extra: vec![("ext.damping".into(), vec![2, 2], vec![1.0, 0.5, 0.0, 1.0])], ..cfg.clone() }, "symmetric"),
        (SynthConfig { lim: false, meta: vec![("lim".into(), "true".into())], ..cfg.clone() }, "lim.0.weight"),
    ];
    for (c, want) in cases {
        let e = Model::from_bytes(&random_weights(&c)).expect_err(want).to_string();
        assert!(e.contains(want), "error {e:?} should mention {want:?}");
    }
    // dtype: rewrite one tensor as F32 in place (same byte size for half the elements is not valid, so
    // write a separate F32 tensor file)
    use safetensors::tensor::{Dtype, TensorView};
    let data = vec![0u8; 4 * 3];
    let v = TensorView::new(Dtype::F32, vec![3], &data).unwrap();
    let mut meta = std::collections::HashMap::new();
    meta.insert("format".to_string(), "exolan-weights".to_string());
    meta.insert("format_version".to_string(), "1".to_string());
    let b = safetensors::serialize(vec![("delan.L.2.bias".to_string(), v)], Some(meta)).unwrap();
    assert!(Model::from_bytes(&b).is_err());
}
