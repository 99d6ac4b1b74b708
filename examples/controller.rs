//! A native 200 Hz controller loop with no Python: load an exported model, replay a recorded trial
//! (layout 1, `Exo.csv`) sample by sample, and estimate the human joint torque online:
//!
//!   x_t   = [q, q̇, f_v, CoP·(f_v > 20 N)]             (context features, DESIGN.md section 1)
//!   z_t   = encoder.step(x_t)                          (streaming TCN/LSTM, ring buffers)
//!   q̈_t   = low-pass((q̇_t − q̇_{t−1}) / dt)            (causal filtered difference)
//!   τ_h,t = model.inverse(q_t, q̇_t, q̈_t, z_t, f_v,t) − τ_e,t   (model torque − recorded exo torque)
//!
//! and print the per-step latency distribution (sample in → τ_h out). With the trial's
//! `Joint_Moments_Filt.csv` and `subjects.csv` present, it also reports the estimate's RMSE against
//! the recorded human moment.
//!
//!     cargo run --release --no-default-features --example controller -- MODEL.safetensors TRIAL_DIR [--side l|r] [--realtime] [--cutoff HZ]
//!     cargo run --release --no-default-features --example controller -- --synthetic TRIAL_DIR   (random weights)

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use exolan::synth::{random_weights, SynthConfig};
use exolan::Model;

/// Columns of a CSV by header name; empty or unparsable cells are NaN.
fn read_csv(path: &Path) -> Result<HashMap<String, Vec<f64>>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().ok_or("empty file")?.split(',').map(|s| s.trim().to_string()).collect();
    let mut cols: Vec<Vec<f64>> = vec![vec![]; header.len()];
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let cells: Vec<&str> = line.split(',').collect();
        for (i, col) in cols.iter_mut().enumerate() {
            col.push(cells.get(i).and_then(|c| c.trim().parse::<f64>().ok()).unwrap_or(f64::NAN));
        }
    }
    Ok(header.into_iter().zip(cols).collect())
}

fn col<'a>(c: &'a HashMap<String, Vec<f64>>, name: &str, file: &str) -> &'a [f64] {
    c.get(name).unwrap_or_else(|| panic!("{file}: missing column {name}"))
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// The command line, with the model loaded and checked.
struct Args {
    model: Model,
    trial_dir: PathBuf,
    side: String,
    cutoff: f64,
    realtime: bool,
}

fn parse_args() -> Args {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let flag = |name: &str| args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).cloned();
    let positional: Vec<&String> = {
        let mut v = vec![];
        let mut skip = false;
        for a in &args {
            if skip {
                skip = false;
                continue;
            }
            if a == "--side" || a == "--cutoff" {
                skip = true;
            } else if !a.starts_with("--") {
                v.push(a);
            }
        }
        v
    };
    let synthetic = args.iter().any(|a| a == "--synthetic");
    let realtime = args.iter().any(|a| a == "--realtime");
    let side = flag("--side").unwrap_or_else(|| "r".into());
    let cutoff: f64 = flag("--cutoff").and_then(|s| s.parse().ok()).unwrap_or(25.0);
    let (model, trial_dir) = match (synthetic, positional.as_slice()) {
        (true, [dir]) => (Model::from_bytes(&random_weights(&SynthConfig::default())).unwrap(), PathBuf::from(dir)),
        (false, [m, dir]) => match Model::load(m) {
            Ok(model) => (model, PathBuf::from(dir)),
            Err(e) => {
                eprintln!("controller: {e}");
                std::process::exit(2);
            }
        },
        _ => {
            eprintln!("usage: controller MODEL.safetensors TRIAL_DIR [--side l|r] [--realtime] [--cutoff HZ]\n       controller --synthetic TRIAL_DIR");
            std::process::exit(2);
        }
    };
    if model.n != 2 {
        eprintln!("controller: the exoskeleton loop needs a hip + knee model, this one has {} joints", model.n);
        std::process::exit(2);
    }
    let expected = ["q_hip", "q_knee", "qd_hip", "qd_knee", "f_v", "cop_x", "cop_z"];
    if model.dz > 0 && !synthetic && model.meta.context_channels != expected {
        eprintln!("controller: model context channels {:?} are not the layout-1 ones {expected:?}", model.meta.context_channels);
        std::process::exit(2);
    }

    Args { model, trial_dir, side, cutoff, realtime }
}

/// The recorded channels of one leg (degrees and N m as in the file).
struct Trial {
    time: Vec<f64>,
    q: [Vec<f64>; 2],
    qd: [Vec<f64>; 2],
    f_v: Vec<f64>,
    cop: [Vec<f64>; 2],
    te: [Vec<f64>; 2],
}

fn read_trial(trial_dir: &std::path::Path, s: &str) -> Trial {
    let exo_path = trial_dir.join("Exo.csv");
    let exo = read_csv(&exo_path).unwrap_or_else(|e| {
        eprintln!("controller: {e}");
        std::process::exit(2)
    });
    let f = "Exo.csv";
    let time = col(&exo, "time", f);
    let q_hip = col(&exo, &format!("hip_angle_{s}"), f);
    let q_knee = col(&exo, &format!("knee_angle_{s}"), f);
    let qd_hip = col(&exo, &format!("hip_angle_{s}_velocity_filt"), f);
    let qd_knee = col(&exo, &format!("knee_angle_{s}_velocity_filt"), f);
    let f_v = col(&exo, &format!("insole_{s}_force_y"), f);
    let cop_x = col(&exo, &format!("insole_{s}_cop_x"), f);
    let cop_z = col(&exo, &format!("insole_{s}_cop_z"), f);
    let te_hip = col(&exo, &format!("hip_angle_{s}_torque_measured"), f);
    let te_knee = col(&exo, &format!("knee_angle_{s}_torque_measured"), f);
    if time.len() < 2 {
        eprintln!("controller: {} has fewer than 2 samples", exo_path.display());
        std::process::exit(2);
    }
    let v = <[f64]>::to_vec;
    Trial {
        time: v(time),
        q: [v(q_hip), v(q_knee)],
        qd: [v(qd_hip), v(qd_knee)],
        f_v: v(f_v),
        cop: [v(cop_x), v(cop_z)],
        te: [v(te_hip), v(te_knee)],
    }
}

/// What the loop produced: the human torque estimate per sample, per-step latencies (µs), samples
/// skipped, wall time.
struct Run {
    tau_h: Vec<[f64; 2]>,
    latency: Vec<f64>,
    skipped: usize,
    wall: f64,
}

/// The controller loop over the recorded samples.
fn run(model: &Model, tr: &Trial, dt: f64, cutoff: f64, realtime: bool) -> Run {
    let n_samples = tr.time.len();
    let deg = std::f64::consts::PI / 180.0;
    // first-order low-pass on the velocity difference: a = dt / (dt + 1/(2π f_c))
    let alpha = dt / (dt + 1.0 / (2.0 * std::f64::consts::PI * cutoff));

    // --- everything the loop touches is allocated here ---
    let mut ws = model.workspace();
    let mut enc = model.encoder_state();
    let mut z = vec![0.0; model.dz];
    let mut x = vec![0.0; 7];
    let mut qdd: [f64; 2] = [0.0; 2];
    let mut qd_prev = [f64::NAN; 2];
    let mut tau_model = [0.0; 2];
    let mut tau_h = vec![[f64::NAN; 2]; n_samples];
    let mut latency = Vec::with_capacity(n_samples);
    let mut skipped = 0usize;
    let period = Duration::from_secs_f64(dt);
    let start = Instant::now();

    for t in 0..n_samples {
        if realtime {
            // wait for the sample's tick, as a controller clocked by its sensors would
            let due = start + period.mul_f64(t as f64);
            while Instant::now() < due {
                std::hint::spin_loop();
            }
        }
        let t0 = Instant::now();
        let q = [tr.q[0][t] * deg, tr.q[1][t] * deg];
        let qd = [tr.qd[0][t] * deg, tr.qd[1][t] * deg];
        let fv = tr.f_v[t];
        let loaded = fv > 20.0;
        x.copy_from_slice(&[q[0], q[1], qd[0], qd[1], fv, if loaded { tr.cop[0][t] } else { 0.0 }, if loaded { tr.cop[1][t] } else { 0.0 }]);
        // the encoder sees every sample (NaN channels become 0 after normalisation)
        if model.dz > 0 {
            model.encode_step(&mut enc, &x, &mut z).unwrap();
            ws.set_z(model, &z).unwrap();
        }
        for i in 0..2 {
            let raw = if qd_prev[i].is_finite() && qd[i].is_finite() { (qd[i] - qd_prev[i]) / dt } else { 0.0 };
            qdd[i] = if qdd[i].is_finite() { qdd[i] + alpha * (raw - qdd[i]) } else { raw };
            qd_prev[i] = qd[i];
        }
        let te = [tr.te[0][t], tr.te[1][t]];
        let usable = q.iter().chain(&qd).chain(&te).all(|v| v.is_finite()) && fv.is_finite();
        if usable {
            let f_in = if model.meta.lim { fv } else { 0.0 };
            if model.inverse_dynamics(&mut ws, &q, &qd, &qdd, f_in, None, &mut tau_model).is_ok() {
                tau_h[t] = [tau_model[0] - te[0], tau_model[1] - te[1]];
            }
        } else {
            skipped += 1;
        }
        latency.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    let wall = start.elapsed().as_secs_f64();

    Run { tau_h, latency, skipped, wall }
}

fn main() {
    let Args { model, trial_dir, side, cutoff, realtime } = parse_args();
    let s = side.as_str();
    let tr = read_trial(&trial_dir, s);
    let n_samples = tr.time.len();
    let dt = (tr.time[n_samples - 1] - tr.time[0]) / (n_samples - 1) as f64;
    let Run { tau_h, latency, skipped, wall } = run(&model, &tr, dt, cutoff, realtime);
    let mut sorted = latency.clone();
    sorted.sort_by(f64::total_cmp);
    println!("model: {} (lim {}, encoder {:?}, simd {:?}); trial {} side {s}", model.meta.method, model.meta.lim, model.meta.encoder, model.simd(), trial_dir.display());
    println!("{n_samples} samples at {:.0} Hz ({:.2} s of data) in {wall:.3} s wall{}; {skipped} samples skipped (NaN)", 1.0 / dt, dt * (n_samples - 1) as f64, if realtime { " (real time)" } else { "" });
    println!(
        "per-step latency (encoder + z + q̈ filter + inverse dynamics): p50 {:.2} µs  p90 {:.2} µs  p99 {:.2} µs  max {:.2} µs  (budget at 200 Hz: {:.0} µs)",
        percentile(&sorted, 0.5),
        percentile(&sorted, 0.9),
        percentile(&sorted, 0.99),
        sorted[sorted.len() - 1],
        dt * 1e6
    );

    compare_moments(&trial_dir, s, n_samples, &tau_h);
}

/// Where the recording has them: RMSE of τ_h against the recorded human moment (N m/kg x body mass).
fn compare_moments(trial_dir: &std::path::Path, s: &str, n_samples: usize, tau_h: &[[f64; 2]]) {
    let moments = trial_dir.join("Joint_Moments_Filt.csv");
    let subjects = trial_dir.parent().and_then(|p| p.parent()).map(|p| p.join("subjects.csv"));
    let subject = trial_dir.parent().and_then(|p| p.file_name()).map(|s| s.to_string_lossy().to_string());
    if let (Ok(m), Some(Ok(sub)), Some(subject)) = (read_csv(&moments), subjects.map(std::fs::read_to_string), subject) {
        let mass = sub
            .lines()
            .skip(1)
            .find_map(|l| {
                let c: Vec<&str> = l.split(',').collect();
                (c.first() == Some(&subject.as_str())).then(|| c.get(1).and_then(|v| v.trim().parse::<f64>().ok())).flatten()
            });
        let hip = m.get(&format!("hip_flexion_{s}_moment"));
        let knee = m.get(&format!("knee_angle_{s}_moment"));
        if let (Some(mass), Some(hip), Some(knee)) = (mass, hip, knee) {
            for (j, name, label) in [(0, "hip", hip), (1, "knee", knee)] {
                let (mut se, mut ss, mut cnt) = (0.0, 0.0, 0usize);
                for t in 0..n_samples.min(label.len()) {
                    let y = label[t] * mass;
                    if tau_h[t][j].is_finite() && y.is_finite() {
                        se += (tau_h[t][j] - y).powi(2);
                        ss += y * y;
                        cnt += 1;
                    }
                }
                if cnt > 0 {
                    println!("human torque estimate, {name}: RMSE {:.2} N m vs recorded moment (RMS {:.2} N m, {cnt} samples)", (se / cnt as f64).sqrt(), (ss / cnt as f64).sqrt());
                }
            }
        }
    }
}
