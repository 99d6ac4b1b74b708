"""Probe: the diagnosis of a slow-suite-shaped world (2 users x walk, squat, calisthenics, turn x 16 s, the tests'
settings) with rule 3's tracking-lag null for a gain left out (`nulls.track_lag` patched to the residual's lag in
this process only). argv: NAME SEED [EFFECT ...]; the world is simulated under $TMPDIR/NAME once; or WORLD_DIR
OUT: that world at the CLI's defaults. Reads no truth."""
import sys
import tempfile
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))
from exolan.world import simulate
from exolan.diagnose import diagnose, nulls
import test_diagnose as td
orig = nulls.nulls_of
def patched(ss, entry):
    nulls.track_lag = lambda flat, j, max_lag=40: nulls.leak_lag(ss.ref, flat, j)
    return orig(ss, entry)
nulls.nulls_of = patched
if Path(sys.argv[1]).is_dir():                 # an existing world: the CLI's defaults, as `exolan diagnose W --out D`
    from exolan.cli import main
    sys.exit(main(["diagnose", sys.argv[1], "--out", sys.argv[2]]))
name, seed, eff = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
root = Path(tempfile.gettempdir()) / name
if not root.exists():
    simulate(root, users=2, tasks=td.WORLD_TASKS, seconds=16, seed=seed, effects=eff, progress=False)
rep = diagnose(root, out=root.with_name(f"{name}_nt"), quick=True, verbose=True, **td.WORLD_SETTINGS)
print("FOUND", [(f["effect"], f["joint"], round(f["estimate"], 3)) for f in rep["findings"]])
