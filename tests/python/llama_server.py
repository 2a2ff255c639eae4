#!/usr/bin/env python3
"""llama.cpp's OpenAI-compatible HTTP server (xllamacpp) on loopback, for the tests.

Starts the server on 127.0.0.1 with a free port, prints ONE JSON line to stdout once it is
listening:

    {"url": "http://127.0.0.1:PORT/v1", "model": "...", "n_ctx": N, "n_parallel": N, "threads": N}

then serves until its stdin reaches end of file (the test that started it ended, however it
ended) or it gets SIGTERM or SIGINT, and exits 0. llama.cpp's own log goes to stderr. Errors (no
model file, bad arguments, a server that does not start) go to stderr with a non-zero exit:
2 for bad arguments, 1 otherwise.

Needs the venv of tests/python/setup.sh (xllamacpp, pinned in requirements-llama.txt).
"""

import argparse
import json
import os
import signal
import sys


def positive(text):
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not a positive integer")
    return value


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="the GGUF model file")
    parser.add_argument("--n-ctx", type=positive, default=4096, help="context size in tokens, shared by the slots (default 4096)")
    parser.add_argument("--threads", type=positive, default=2, help="CPU threads for prefill and decode (default 2)")
    parser.add_argument("--n-parallel", type=positive, default=1, help="slots: requests served at once (default 1)")
    parser.add_argument("--alias", help="the model name the server reports (default: llama.cpp's, from the file)")
    args = parser.parse_args()

    if not os.path.isfile(args.model):
        print(f"llama_server.py: no model file at {args.model}", file=sys.stderr)
        return 1

    try:
        import xllamacpp as xlc
    except ImportError as e:
        print(f"llama_server.py: cannot import xllamacpp ({e}): run bash tests/python/setup.sh", file=sys.stderr)
        return 1

    # SIGTERM and SIGINT end the wait below as end of input does.
    def stop(signum, _frame):
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)

    params = xlc.CommonParams()
    params.model.path = args.model
    params.n_ctx = args.n_ctx
    params.n_parallel = args.n_parallel
    params.cpuparams.n_threads = args.threads
    params.cpuparams_batch.n_threads = args.threads
    params.hostnames = ["127.0.0.1"]
    params.port = 0  # a free one; the bound address is in listening_address
    if args.alias:
        params.model_alias = {args.alias}

    try:
        server = xlc.Server(params)
    except RuntimeError as e:
        # llama.cpp has logged why (e.g. "failed to load model") on stderr just before.
        print(f"llama_server.py: the server did not start for {args.model}: {e}", file=sys.stderr)
        return 1

    # e.g. "http://127.0.0.1:42329": the server's root; the OpenAI API is under /v1.
    address = server.listening_address
    if not address.startswith("http://"):
        print(f"llama_server.py: unexpected listening address {address!r}", file=sys.stderr)
        return 1
    ready = {
        "url": address.rstrip("/") + "/v1",
        "model": args.alias or os.path.basename(args.model),
        "n_ctx": args.n_ctx,
        "n_parallel": args.n_parallel,
        "threads": args.threads,
    }
    print(json.dumps(ready), flush=True)

    try:
        # Returns at end of input: whoever started us is gone or done.
        sys.stdin.buffer.read()
    except SystemExit:
        pass
    # Not `del server`: xllamacpp's Server destructor waits for ever while a request is being
    # generated (seen with 2026.10.11549: "cleaning up before exit..." and no exit). The server
    # holds nothing that needs flushing, so the process ends at once and the OS frees the rest.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
