#!/usr/bin/env bash
# CI of the C# binding (client/csharp), run by client/rust/ci.sh after its cargo test (it reuses
# that build's debug libdrape.so and its running server), or alone from any directory:
#   bash client/csharp/ci.sh
# Installs Mono from Debian when mcs or mono is missing (apt-get update once, then
# apt-get install mono-devel; no NuGet), compiles Runtime/Core (the engine-independent core of the
# Unity package) into Drape.dll and tests/Tests.cs against it with mcs, type-checks
# Runtime/DrapeCloth.cs against stubs of the Unity API it uses (tests/unity-stubs), compiles tests/layout.c
# against drape.h, and runs the tests under Mono against a real `drape serve`: $DRAPE_ENDPOINT
# when set (a server already up), else one started here from $DRAPE_BIN (default
# <repo>/.venv/bin/drape). The library: $DRAPE_LIB_DIR (default client/rust/target/debug; built
# with `cargo build -j 2 --locked --lib` when missing). Exits non-zero on any failure.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
crate="$repo/client/rust"
export DRAPE_BIN="${DRAPE_BIN:-$repo/.venv/bin/drape}"
libdir="${DRAPE_LIB_DIR:-${CARGO_TARGET_DIR:-$crate/target}/debug}"
start=$SECONDS
step() { echo "== csharp [$((SECONDS - start)) s] $*"; }
die() { echo "csharp/ci.sh: FAILED: $*" >&2; exit 1; }

step "tools"
if ! command -v mcs >/dev/null || ! command -v mono >/dev/null; then
    command -v apt-get >/dev/null || die "mono and mcs are missing and there is no apt-get (install Mono: mono-devel)"
    echo "installing Mono from Debian (mono-devel)"
    sudo_="" ; [[ $(id -u) -ne 0 ]] && sudo_="sudo"
    $sudo_ apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_ apt-get install -y -qq --no-install-recommends mono-devel >/dev/null
fi
mono --version | head -1
if [[ ! -f "$libdir/libdrape.so" ]]; then
    step "cargo build --lib (debug)"
    (cd "$crate" && cargo build -j 2 --locked --lib)
fi

step "compile (mcs)"
build="$here/build"
rm -rf "$build"
mkdir -p "$build"
${CC:-cc} -std=c11 -Wall -I "$crate/include" "$here/tests/layout.c" -o "$build/layout"
"$build/layout" > "$build/layout.txt"
mcs -nologo -unsafe -langversion:experimental -target:library -warnaserror -out:"$build/Drape.dll" \
    "$here"/unity/com.drape.client/Runtime/Core/*.cs
mcs -nologo -unsafe -langversion:experimental -r:"$build/Drape.dll" -out:"$build/Tests.exe" "$here/tests/Tests.cs"
# the Unity component against stubs of the Unity API it uses (a type check only: not Unity)
mcs -nologo -unsafe -langversion:experimental -target:library -out:"$build/UnityStubs.dll" "$here/tests/unity-stubs/UnityStubs.cs"
mcs -nologo -unsafe -langversion:experimental -target:library -warnaserror -define:UNITY_5_3_OR_NEWER \
    -r:"$build/UnityStubs.dll" -r:"$build/Drape.dll" -out:"$build/DrapeUnity.dll" "$here/unity/com.drape.client/Runtime/DrapeCloth.cs"
cp "$libdir/libdrape.so" "$build/"

free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
if [[ -z "${DRAPE_ENDPOINT:-}" ]]; then
    step "drape serve"
    [[ -x "$DRAPE_BIN" ]] || die "the drape server $DRAPE_BIN is missing (run \`bash deploy/setup.sh test\` first, or set DRAPE_BIN)"
    port="$(free_port)"
    log="$(mktemp)"
    "$DRAPE_BIN" serve --listen "tcp/127.0.0.1:$port" --server-id "ci-cs-$port" --no-admission >"$log" 2>&1 &
    server=$!
    trap 'kill "$server" 2>/dev/null || true; rm -f "$log"' EXIT
    DRAPE_ENDPOINT="tcp/127.0.0.1:$port"
    # the client's open waits (up to 120 s here) for the server's liveliness token
fi

step "mono Tests.exe against $DRAPE_ENDPOINT"
closed="tcp/127.0.0.1:$(free_port)"   # nothing listens there
cd "$build"
if ! LD_LIBRARY_PATH="$build${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" timeout 300 mono --debug Tests.exe "$DRAPE_ENDPOINT" layout.txt "$closed"; then
    [[ -n "${log:-}" ]] && { echo "server log:" >&2; tail -40 "$log" >&2; }
    die "C# tests after $((SECONDS - start)) s"
fi
step "C# tests passed"
