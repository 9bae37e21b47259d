#!/usr/bin/env bash
# Build the drape C library once and package it for C/C++ projects:
#   client/rust/package.sh [--profile dist|dev|NAME] [--out DIR]
# builds the library once: with the default profile `dist` (release + thin LTO, Cargo.toml)
# `cargo rustc --locked -j ${JOBS:-2} --lib --profile dist --crate-type cdylib --crate-type
# staticlib` (LTO keeps only the code the C ABI reaches); with another profile `cargo build
# --locked -j ${JOBS:-2} --lib --profile P` (a no-op when current: CI packages the dev build its
# `cargo test` made). FEATURES (default: the crate's, TLS included) are passed as --features
# after --no-default-features when set, e.g. FEATURES=client. Then it writes
#   DIR/drape-<version>-<target>[-<profile>].tar.gz   (DIR default: target/archive)
# holding drape-<version>/{include/drape.h, lib/libdrape.so, lib/libdrape.a,
# lib/pkgconfig/drape.pc, lib/cmake/drape/drapeConfig.cmake + drapeConfigVersion.cmake,
# share/doc/drape/README.md}. Relocatable: extract anywhere, then
#   cmake -DCMAKE_PREFIX_PATH=/that/drape-<version> ...   and   find_package(drape REQUIRED)
#   target_link_libraries(game PRIVATE drape::drape)          # shared (drape::drape_static: static)
# or PKG_CONFIG_PATH=/that/drape-<version>/lib/pkgconfig pkg-config --cflags --libs drape
# (--static for the static library). Prints the archive's path and size last.
set -euo pipefail
crate="$(cd "$(dirname "$0")" && pwd)"
profile=dist
out="${CARGO_TARGET_DIR:-$crate/target}/archive"
while (($#)); do
    case "$1" in
        --profile) profile="$2"; shift 2 ;;
        --release) profile=dist; shift ;;
        --out) out="$2"; shift 2 ;;
        -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
        *) echo "package.sh: unknown argument $1" >&2; exit 2 ;;
    esac
done
version="$(sed -n 's/^version = "\(.*\)"/\1/p' "$crate/Cargo.toml" | head -1)"
target_triple="$(rustc -vV | sed -n 's/^host: //p')"
dir_of_profile() { case "$1" in dev|test) echo debug ;; bench) echo release ;; *) echo "$1" ;; esac; }
built="${CARGO_TARGET_DIR:-$crate/target}/$(dir_of_profile "$profile")"
features=()
[[ -n "${FEATURES:-}" ]] && features=(--no-default-features --features "$FEATURES")

if [[ "$profile" == dist ]]; then
    cargo rustc --locked -j "${JOBS:-2}" --lib --profile dist "${features[@]}" --crate-type cdylib --crate-type staticlib \
        --manifest-path "$crate/Cargo.toml"
else
    cargo build --locked -j "${JOBS:-2}" --lib --profile "$profile" "${features[@]}" --manifest-path "$crate/Cargo.toml"
fi

name="drape-$version"
suffix=""; [[ "$profile" != dist ]] && suffix="-$profile"
stage="$(mktemp -d)"
trap 'rm -rf "$stage"' EXIT
root="$stage/$name"
mkdir -p "$root/include" "$root/lib/pkgconfig" "$root/lib/cmake/drape" "$root/share/doc/drape"
cp "$crate/include/drape.h" "$root/include/"
cp "$built/libdrape.a" "$built/libdrape.so" "$root/lib/"
# the static library carries the debug info of Rust's std (about 7 MB): not for shipping
[[ "$profile" == dist ]] && strip --strip-debug "$root/lib/libdrape.a"
cp "$crate/README.md" "$root/share/doc/drape/README.md"
# the system libraries Rust's std needs when linking the static library (Linux, glibc)
private_libs="-lgcc_s -lutil -lrt -lpthread -lm -ldl -lc"

cat > "$root/lib/pkgconfig/drape.pc" <<PC
prefix=\${pcfiledir}/../..
libdir=\${prefix}/lib
includedir=\${prefix}/include

Name: drape
Description: C client of the Drape cloth service (Zenoh); protocol 1.4
Version: $version
Cflags: -I\${includedir}
Libs: -L\${libdir} -Wl,-rpath,\${libdir} -ldrape
Libs.private: $private_libs
PC

cat > "$root/lib/cmake/drape/drapeConfig.cmake" <<'CMAKE'
# drapeConfig.cmake: the drape C library (client/rust package.sh). Targets:
#   drape::drape         the shared library (libdrape.so)
#   drape::drape_static  the static library (libdrape.a) with the system libraries it needs
get_filename_component(_drape_prefix "${CMAKE_CURRENT_LIST_DIR}/../../.." ABSOLUTE)
if(NOT TARGET drape::drape)
  add_library(drape::drape SHARED IMPORTED)
  set_target_properties(drape::drape PROPERTIES
    IMPORTED_LOCATION "${_drape_prefix}/lib/libdrape.so"
    IMPORTED_NO_SONAME TRUE
    INTERFACE_INCLUDE_DIRECTORIES "${_drape_prefix}/include")
  add_library(drape::drape_static STATIC IMPORTED)
  set_target_properties(drape::drape_static PROPERTIES
    IMPORTED_LOCATION "${_drape_prefix}/lib/libdrape.a"
    INTERFACE_INCLUDE_DIRECTORIES "${_drape_prefix}/include"
    INTERFACE_LINK_LIBRARIES "gcc_s;util;rt;pthread;m;dl;c")
endif()
set(drape_INCLUDE_DIRS "${_drape_prefix}/include")
set(drape_LIBRARIES drape::drape)
unset(_drape_prefix)
CMAKE

cat > "$root/lib/cmake/drape/drapeConfigVersion.cmake" <<CMAKE
set(PACKAGE_VERSION "$version")
if(PACKAGE_FIND_VERSION VERSION_GREATER PACKAGE_VERSION)
  set(PACKAGE_VERSION_COMPATIBLE FALSE)
else()
  string(REGEX MATCH "^[0-9]+\\\\.[0-9]+" _have "\${PACKAGE_VERSION}")
  string(REGEX MATCH "^[0-9]+\\\\.[0-9]+" _want "\${PACKAGE_FIND_VERSION}")
  if(PACKAGE_FIND_VERSION STREQUAL "" OR _have STREQUAL _want)
    set(PACKAGE_VERSION_COMPATIBLE TRUE)  # 0.x: the same minor
  else()
    set(PACKAGE_VERSION_COMPATIBLE FALSE)
  endif()
  if(PACKAGE_FIND_VERSION STREQUAL PACKAGE_VERSION)
    set(PACKAGE_VERSION_EXACT TRUE)
  endif()
endif()
CMAKE

mkdir -p "$out"
archive="$out/$name-$target_triple$suffix.tar.gz"
tar -C "$stage" -czf "$archive" "$name"
echo "libdrape.a $(stat -c %s "$root/lib/libdrape.a") bytes, libdrape.so $(stat -c %s "$root/lib/libdrape.so") bytes"
echo "$archive $(stat -c %s "$archive") bytes"
