#!/usr/bin/env bash
# CI for the Rust client (run after the Python tests, from any directory):
#   client/rust/ci.sh
# Builds the crate, runs `cargo test` (protocol vectors, header check, live tests against a
# real `drape serve`), then builds the C example against the static library and runs it
# against a `drape serve` started here. Exits non-zero on any failure. The server binary is
# $DRAPE_BIN (default: <repo>/.venv/bin/drape); CI=true (the default here) makes a missing
# server a test failure rather than a skip.
set -euo pipefail
crate="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$crate/../.." && pwd)"
export CI="${CI:-true}"
export DRAPE_BIN="${DRAPE_BIN:-$repo/.venv/bin/drape}"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
cd "$crate"

echo "== cargo test (vectors, header, live tests with $DRAPE_BIN)"
cargo test -j 2 --locked

echo "== C example"
examples/c/build.sh
if [[ ! -x "$DRAPE_BIN" ]]; then
    echo "ci.sh: the drape server $DRAPE_BIN is missing (create the venv first)" >&2
    exit 1
fi
port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
log="$(mktemp)"
"$DRAPE_BIN" serve --listen "tcp/127.0.0.1:$port" --server-id "ci-c-$port" >"$log" 2>&1 &
server=$!
trap 'kill "$server" 2>/dev/null || true; rm -f "$log"' EXIT
if ! timeout 120 examples/c/build/cape "tcp/127.0.0.1:$port" 60; then
    echo "ci.sh: the C example failed; server log:" >&2
    cat "$log" >&2
    exit 1
fi
echo "ci.sh: all Rust client checks passed"
