import sys, json
from pathlib import Path
from exolan.diagnose import diagnose
root, out = Path(sys.argv[1]), Path(sys.argv[2])
rep = diagnose(root, out=out, quick=True, verbose=True, steps_base=1500, steps_refit=400, hidden=64, inject_delay=True)
print("FOUND", [(f["effect"], f["joint"], round(f["estimate"], 4)) for f in rep["findings"]])
print("LIMITS", json.dumps(rep["detection_limits"]["actuation_delay"], default=str))
