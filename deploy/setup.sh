#!/usr/bin/env bash
# Set up Drape in ./.venv on a fresh machine: the package with the server, tools and (with
# `test`) test extras from PyPI, then prove an OpenCL device: `drape devices --check` builds and
# runs every kernel the server runs (the CPU pack solver at each width it may use) on every
# device, each in a child process, and says which device, driver and pack width Drape will use.
# The PoCL inside the pyopencl wheel carries LLVM 14: it builds nothing on a CPU newer than it
# (AMD Zen 5: "unknown target CPU 'generic'") and aborts on the 16-lane pack kernel on some
# AVX-512 CPUs it knows by an older name (Zen 4). When no device passes, or the only CPU device
# passes with narrower packs only, this installs Debian's pocl-opencl-icd (with apt and root)
# and checks again; Drape then picks the device that runs the widest packs.
#   bash deploy/setup.sh          # server + tools (the demo)
#   bash deploy/setup.sh test     # + pytest, ruff, mypy
set -euo pipefail
cd "$(dirname "$0")/.."
extras="server,tools"
[[ "${1:-}" == "test" ]] && extras="server,tools,test"
python3 -m venv .venv
# an editable install of this checkout under the old distribution name (it was "drape", which
# is another project on the package index) would shadow the new one's `drape` command
if .venv/bin/pip show drape 2>/dev/null | grep -qx "Editable project location: $PWD"; then
    .venv/bin/pip uninstall -q -y drape
fi
.venv/bin/pip install -q --disable-pip-version-check -e ".[${extras}]"

check() { .venv/bin/drape --log-level error devices --check; }
narrow() { grep -q "^chosen: .*CPU pack lanes [0-8])$" <<<"$1"; }

echo "setup: checking the OpenCL devices (building and running Drape's kernels)"
if out=$(check); then
    echo "$out" | sed 's/^/setup: /'
    if ! narrow "$out"; then
        exit 0
    fi
    echo "setup: the chosen CPU device runs only narrow packs (its compiler fails on 16 lanes)"
else
    echo "$out" | sed 's/^/setup: /'
    echo "setup: no OpenCL device runs Drape's kernels"
fi
if command -v apt-get >/dev/null && [[ $(id -u) == 0 ]]; then
    echo "setup: installing Debian's pocl-opencl-icd and checking again"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq pocl-opencl-icd) >/dev/null
    if out=$(check); then
        echo "$out" | sed 's/^/setup: /'
        exit 0
    fi
    echo "$out" | sed 's/^/setup: /'
elif narrow "${out:-}"; then
    echo "setup: using the narrower packs (no apt-get as root to install Debian's pocl-opencl-icd)"
    exit 0
fi
echo "setup: no OpenCL device can run Drape's kernels; install a PoCL that knows this CPU (Debian: pocl-opencl-icd) or a GPU driver" >&2
exit 1
