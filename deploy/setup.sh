#!/usr/bin/env bash
# Set up Drape in ./.venv on a fresh machine: the package with the server, tools and (with
# `test`) test extras from PyPI, then check that an OpenCL device can build kernels. The PoCL
# inside the pyopencl wheel carries LLVM 14, which does not know CPUs newer than it (AMD Zen 5
# fails with "unknown target CPU 'generic'"); on such a machine, with apt and root, this installs
# Debian's pocl-opencl-icd beside it, and Drape picks the device that builds.
#   bash deploy/setup.sh          # server + tools (the demo)
#   bash deploy/setup.sh test     # + pytest, ruff, mypy
set -euo pipefail
cd "$(dirname "$0")/.."
extras="server,tools"
[[ "${1:-}" == "test" ]] && extras="server,tools,test"
python3 -m venv .venv
.venv/bin/pip install -q --disable-pip-version-check -e ".[${extras}]"

probe() { .venv/bin/python -c 'from drape.server.sim.opencl.device import Device; print(Device().info.name)' 2>/dev/null; }
if dev=$(probe); then
    echo "setup: OpenCL device: ${dev}"
    exit 0
fi
if command -v apt-get >/dev/null && [[ $(id -u) == 0 ]]; then
    echo "setup: no OpenCL device builds kernels; installing Debian's pocl-opencl-icd"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq pocl-opencl-icd) >/dev/null
    if dev=$(probe); then
        echo "setup: OpenCL device: ${dev}"
        exit 0
    fi
fi
echo "setup: no OpenCL device can build kernels; install a PoCL that knows this CPU (Debian: pocl-opencl-icd) or a GPU driver" >&2
exit 1
