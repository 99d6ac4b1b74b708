import sys, json
from pathlib import Path
from exolan.world import simulate
from exolan.diagnose import diagnose
case_eff, seed, value, out = sys.argv[1], int(sys.argv[2]), sys.argv[3], Path(sys.argv[4])
root = out / "world"
if not root.exists():
    simulate(root, users=2, tasks="walk,squat,calisthenics,turn", seconds=16, seed=seed, effects=[f"{case_eff}:{value}"], progress=False)
rep = diagnose(root, out=out / "diag", quick=True, verbose=True, steps_base=1500, steps_refit=400, hidden=64)
print("FOUND", [(f["effect"], f["joint"], round(f["estimate"], 4)) for f in rep["findings"]])
print("LEARNED_CHECK", json.dumps(rep["physics"]["learned_check"] if rep.get("physics") else None))
