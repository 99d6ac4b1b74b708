#!/usr/bin/env bash
# One prepared run on a lent GPU machine (issue 37): `--device cuda` end to end (simulate, train with w_fd and
# w_ms, evaluate), training throughput on the GPU (benches/bench_train.py, this tree and 66a29dd), and the
# converge study on the GPU for a fixed time, whose per-epoch seconds per run give its wall time.
#   OUT=DIR bash scripts/gpu_check.sh [CONVERGE_SECONDS] [WORKERS]     (DEVICE=cpu for a dry run without a GPU)
set -u
OUT=${OUT:-out/gpu_check}
DEVICE=${DEVICE:-cuda}
CONV_S=${1:-270}
WORKERS=${2:-12}
PY=${PYTHON:-python3}
W=${WORK:-/tmp/gpu_check}
mkdir -p "$OUT" "$W"
export PYTHONPATH=$PWD/python PYTHONUNBUFFERED=1 EXOLAN_DEVICE=$DEVICE

step() {   # name, command...: prints the command, its exit status and seconds; never stops the script
    local name=$1 t0=$SECONDS rc
    shift
    echo "== $name: $*"
    "$@"
    rc=$?
    echo "== $name: rc=$rc in $((SECONDS - t0)) s"
}

{
    step env bash -c "nvidia-smi -L; nproc; $PY -c 'import sys, torch; print(sys.version.split()[0], torch.__version__,
torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else \"-\")'"
    step simulate timeout 120 $PY -m exolan.cli simulate --out $W/tiny --users 4 --tasks walk,squat,run --seconds 4 --seed 3
    step train timeout 240 $PY -m exolan.cli train --data $W/tiny --method exolan --w-fd 0.01 --w-ms 1 --epochs 3 \
        --device $DEVICE --out $W/run
    cat $W/run/run.json
    step evaluate timeout 120 $PY -m exolan.cli evaluate $W/run --data $W/tiny --out $OUT/evaluate_tiny.json
    step bench timeout 200 $PY benches/bench_train.py --device $DEVICE --threads 1 --repeats 2 --batches 10 \
        --json $OUT/bench_train_$DEVICE.json
    step converge timeout -k 15 $CONV_S $PY -m exolan.cli reproduce --scale converge --out $W/converge \
        --workers $WORKERS
    # every run's epochs so far and their seconds (a run still training counts too)
    $PY - "$W/converge" "$OUT/converge_epochs.json" <<'PYEOF'
import glob, json, sys
from pathlib import Path
rows = {}
for m in sorted(glob.glob(f"{sys.argv[1]}/runs/*/*/train/metrics.jsonl")):
    d = Path(m).parent
    ep = [json.loads(line) for line in open(m) if line.strip()]
    run = json.loads((d / "run.json").read_text()) if (d / "run.json").exists() else {}
    res = d.parent / "result.json"
    rows[str(d.parent.relative_to(sys.argv[1] + "/runs"))] = dict(
        epochs=len(ep), epoch_seconds=[e["seconds"] for e in ep], device=run.get("device"),
        status=run.get("status"), train_seconds=json.loads(res.read_text())["train_seconds"] if res.exists() else None)
Path(sys.argv[2]).write_text(json.dumps(rows, indent=1))
for k, v in rows.items():
    s = sorted(v["epoch_seconds"])
    print(f"{k:55s} {v['device']} {v['status']} epochs {v['epochs']:3d} median {s[len(s) // 2] if s else float('nan'):.2f} s")
PYEOF
    step bench_old timeout 150 $PY benches/bench_train.py --device $DEVICE --threads 1 --repeats 1 --batches 10 \
        --against 66a29dd --json $OUT/bench_train_${DEVICE}_vs_66a29dd.json
} 2>&1 | tee "$OUT/gpu_check.log"
