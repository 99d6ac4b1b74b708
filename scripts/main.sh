#!/usr/bin/env bash
# The main job, end to end on built-in defaults:
# simulated data -> train -> evaluate -> export -> Rust rollouts -> diagnose -> report.
# Usage: bash scripts/main.sh [OUT_DIR]   (default: out/main)
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
OUT="${1:-out/main}"
exolan doctor
exolan pipeline --out "$OUT"
