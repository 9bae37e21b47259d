#!/usr/bin/env bash
# CI for the Rust client (run after `bash deploy/setup.sh test` created <repo>/.venv, from any
# directory):
#   bash client/rust/ci.sh
# Checks the tools, builds the crate (also without the Zenoh client), runs `cargo test`
# (protocol vectors of every version, hostile input, drape_wire.h layouts, the C header, live
# tests against real `drape serve` processes), packages the library `cargo test` built (the dev
# profile: no second build) with package.sh, builds the C examples with CMake from that archive
# (find_package(drape)), runs them against a `drape serve` started here (cape.c; mesh.c, a cape
# dropped on a mesh collider, no vertex inside; engine.c, 16 capes for 5 s, every state
# accounted for), then the C# binding's tests under Mono against the
# same server and the archive's libdrape.so (client/csharp/ci.sh; it installs Mono from Debian
# when missing). Exits non-zero on any failure. The server binary is $DRAPE_BIN (default:
# <repo>/.venv/bin/drape); CI=true (the default here) makes a missing server a test failure,
# never a skip. Cargo runs with -j 2 and --locked. DRAPE_SKIP_CSHARP=1 skips the C# step.
set -euo pipefail
crate="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$crate/../.." && pwd)"
export CI="${CI:-true}"
export DRAPE_BIN="${DRAPE_BIN:-$repo/.venv/bin/drape}"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
cd "$crate"
start=$SECONDS
failed=()
step() { echo "== [$((SECONDS - start)) s] $*"; }
die() { echo "ci.sh: FAILED: $*" >&2; exit 1; }

step "tools"
for tool in cargo rustc "${CC:-cc}" python3 cmake; do
    command -v "$tool" >/dev/null || die "$tool is not installed"
done
[[ -x "$DRAPE_BIN" ]] || die "the drape server $DRAPE_BIN is missing (run \`bash deploy/setup.sh test\` first, or set DRAPE_BIN)"
"$DRAPE_BIN" serve --help >/dev/null || die "$DRAPE_BIN serve does not start"
[[ -f "$repo/client/protocol/drape_wire.h" && -f "$repo/tests/vectors/control.json" ]] \
    || die "the protocol's vectors or drape_wire.h are missing under $repo"
cargo --version
rustc --version

step "cargo build --no-default-features (the wire layer alone)"
cargo build -j 2 --locked --no-default-features --lib

step "cargo test (vectors, hostile input, layouts, header, live tests with $DRAPE_BIN)"
# every test binary runs (--no-fail-fast); a failure fails ci.sh after the C example has run too
results="$(mktemp)"
if ! cargo test -j 2 --locked --no-fail-fast 2>&1 | tee "$results"; then  # pipefail: cargo's status
    failed+=("cargo test (see the failures above)")
fi
# one closing line for all test binaries (the last binary, the doc-tests, runs none)
summary="$(awk '/^test result:/ {p += $4; f += $6} END {printf "%d passed, %d failed", p, f}' "$results")"
rm -f "$results"

step "package the dev build (package.sh) and build the C examples from the archive with CMake"
work="$(mktemp -d)"
./package.sh --profile dev --out "$work" | tail -2
tar -C "$work" -xzf "$work"/drape-*.tar.gz
prefix="$(echo "$work"/drape-*/)"
cmake -S examples/c -B "$work/build" -DCMAKE_PREFIX_PATH="$prefix" -DCMAKE_BUILD_TYPE=Release >/dev/null
cmake --build "$work/build" -j 2 >/dev/null
port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
log="$(mktemp)"
"$DRAPE_BIN" serve --listen "tcp/127.0.0.1:$port" --server-id "ci-c-$port" >"$log" 2>&1 &
server=$!
trap 'kill "$server" 2>/dev/null || true; rm -rf "$log" "$work"' EXIT
# Up when its liveliness token is seen (up to 120 s: a cold device builds its kernels first).
"$(dirname "$DRAPE_BIN")/python" - "$port" "$server" <<'EOF' || { cat "$log" >&2; die "drape serve did not come up"; }
import os, sys, time, zenoh
port, pid = sys.argv[1], int(sys.argv[2])
c = zenoh.Config()
c.insert_json5("mode", '"peer"')
c.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
c.insert_json5("listen/endpoints", "[]")
c.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(c) as s:
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120:
        os.kill(pid, 0)  # raises when the server exited
        if any(r.ok is not None for r in s.liveliness().get(f"drape/alive/server/ci-c-{port}", timeout=1.0)):
            sys.exit(0)
        time.sleep(0.2)
sys.exit(1)
EOF
step "C examples (CMake, from the archive)"
if ! timeout 120 "$work/build/cape" "tcp/127.0.0.1:$port" 60; then
    echo "ci.sh: the C example failed; server log:" >&2
    cat "$log" >&2
    failed+=("C example")
fi
if ! timeout 120 "$work/build/mesh" "tcp/127.0.0.1:$port" 2; then
    echo "ci.sh: the C mesh collider example failed; server log:" >&2
    tail -40 "$log" >&2
    failed+=("C mesh example")
fi
if ! timeout 180 "$work/build/engine" "tcp/127.0.0.1:$port" 5 16 8; then
    echo "ci.sh: the C engine loop failed; server log:" >&2
    tail -40 "$log" >&2
    failed+=("C engine loop")
fi
if [[ "${DRAPE_SKIP_CSHARP:-}" != 1 ]]; then
    step "C# binding (client/csharp/ci.sh)"
    if ! DRAPE_ENDPOINT="tcp/127.0.0.1:$port" DRAPE_LIB_DIR="$prefix/lib" bash "$repo/client/csharp/ci.sh"; then
        tail -40 "$log" >&2
        failed+=("C# tests")
    fi
fi
if (( ${#failed[@]} )); then
    die "$(printf '%s; ' "${failed[@]}")after $((SECONDS - start)) s"
fi
step "all Rust client checks passed"
echo "rust: ${summary}"
