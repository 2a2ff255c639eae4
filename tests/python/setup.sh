#!/usr/bin/env bash
# Creates (or updates) the Python venv used by the MAVLink interoperability tests and the real
# model-server tests at <repo>/.venv: pymavlink (requirements.txt) and llama.cpp's server
# (requirements-llama.txt, xllamacpp, a prebuilt wheel pinned by its hash).
# Idempotent: re-running it only installs what the requirement files ask for and is missing.
# Needs python3 with the venv module and PyPI (or a mirror configured for pip).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
venv="$repo/.venv"
python="${PYTHON:-python3}"

if ! "$python" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 8) else 1)'; then
    echo "setup.sh: $python is older than 3.8" >&2
    exit 1
fi

if [ ! -x "$venv/bin/python" ]; then
    echo "setup.sh: creating $venv"
    "$python" -m venv "$venv"
fi

"$venv/bin/python" -m pip install --disable-pip-version-check --quiet --upgrade pip
"$venv/bin/python" -m pip install --disable-pip-version-check --quiet -r "$here/requirements.txt"
"$venv/bin/python" -c 'import pymavlink; from pymavlink.dialects.v20 import common; print("setup.sh: pymavlink", pymavlink.__version__ if hasattr(pymavlink, "__version__") else "ok", "ready in '"$venv"'")'
# Hash-checked, wheel only, no dependencies (it has none): nothing is compiled or fetched unpinned.
"$venv/bin/python" -m pip install --disable-pip-version-check --quiet \
    --require-hashes --only-binary :all: --no-deps -r "$here/requirements-llama.txt"
"$venv/bin/python" -c 'import importlib.metadata as m, xllamacpp; print("setup.sh: xllamacpp", m.version("xllamacpp"), "ready in '"$venv"'")'
