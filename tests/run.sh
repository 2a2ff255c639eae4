#!/usr/bin/env bash
# The project's test command (README): sets up the Python MAVLink peer, builds every binary
# (the end-to-end tests start them as processes), and runs every test with nextest.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

bash tests/python/setup.sh
cargo build --workspace --bins
cargo nextest run --workspace --no-fail-fast "$@"
