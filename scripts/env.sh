# Sourced by scripts/main.sh and scripts/test.sh: create or reuse the project-local virtual
# environment, install the pinned dependencies once, and (re)build the Rust extension in release
# mode only when its sources changed. Idempotent: a second run reinstalls nothing.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3}"

if [ ! -x "$VENV/bin/python" ]; then
    echo "[exolan] creating virtual environment in .venv"
    "$PY" -m venv "$VENV"
fi
export VIRTUAL_ENV="$VENV"
export PATH="$VENV/bin:$PATH"

hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }

# 1. Python dependencies (pinned in pyproject.toml), installed once per change of the pins.
deps_stamp="$VENV/.exolan-deps"
deps_hash="$(hash_of pyproject.toml)"
if [ "$(cat "$deps_stamp" 2>/dev/null)" != "$deps_hash" ]; then
    # torch's CUDA build with its nvidia packages takes ~6.5 GB in .venv, ~9.5 GB at the peak of pip's install
    # (measured from a fresh clone, no cache):
    # say so up front rather than leave pip's "No space left on device" halfway through the install
    free_kb="$(df -Pk "$ROOT" | awk 'NR==2 {print $4}')"
    if [ -n "$free_kb" ] && [ "$free_kb" -lt $((10 * 1024 * 1024)) ]; then
        echo "[exolan] warning: $((free_kb / 1024)) MiB free on the disk of $ROOT; the Python dependencies need" \
             "about 10 GiB while they install (6.5 GiB after). Free some space if pip fails." >&2
    fi
    # no pip cache: it would hold a second copy of the ~3 GB of wheels on the same disk
    echo "[exolan] installing pinned Python dependencies (torch included)"
    python -m pip install -q --no-cache-dir pip==26.3
    reqs="$(python - <<'PYEOF'
import tomllib
p = tomllib.load(open("pyproject.toml", "rb"))
deps = p["project"]["dependencies"] + p["project"]["optional-dependencies"]["test"]
deps.append(p["build-system"]["requires"][0])
print("\n".join(deps))
PYEOF
)"
    # shellcheck disable=SC2086
    python -m pip install -q --no-cache-dir $reqs
    echo "$deps_hash" > "$deps_stamp"
fi

# 2. The native extension, built in release mode when the Rust sources or build files changed.
build_stamp="$VENV/.exolan-build"
build_hash="$(hash_of Cargo.toml Cargo.lock pyproject.toml $(find rust -type f | sort))"
if [ "$(cat "$build_stamp" 2>/dev/null)" != "$build_hash" ] || ! python -c "import exolan._native" 2>/dev/null; then
    echo "[exolan] building the Rust extension (release)"
    maturin develop --release --quiet
    echo "$build_hash" > "$build_stamp"
fi
