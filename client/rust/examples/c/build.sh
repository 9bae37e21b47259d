#!/usr/bin/env bash
# Build examples/c/cape.c against the static library: cargo builds libdrape.a, cc links it
# with the system libraries Rust's std needs. Output: examples/c/build/cape.
# Usage: examples/c/build.sh [--release]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
crate="$(cd "$here/../.." && pwd)"
profile=debug
flags=()
if [[ "${1:-}" == "--release" ]]; then profile=release; flags=(--release); fi
cargo build -j 2 --locked --lib "${flags[@]}" --manifest-path "$crate/Cargo.toml"
target="${CARGO_TARGET_DIR:-$crate/target}"
mkdir -p "$here/build"
${CC:-cc} -std=c11 -Wall -Wextra -O2 -I "$crate/include" "$here/cape.c" \
    "$target/$profile/libdrape.a" -lpthread -ldl -lm -lrt -o "$here/build/cape"
echo "built $here/build/cape"
