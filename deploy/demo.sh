#!/usr/bin/env bash
# The main job (README): builds every binary once, then runs `tacos-ground demo` with the
# arguments given, e.g. `deploy/demo.sh --drones 3 --no-llm`.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

cargo build --workspace --bins
# Where cargo put them: `CARGO_TARGET_DIR` when set (relative to this directory, as cargo takes it).
exec "${CARGO_TARGET_DIR:-target}/debug/tacos-ground" demo "$@"
