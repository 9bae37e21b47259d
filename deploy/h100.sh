#!/usr/bin/env bash
# Drape on the lent NVIDIA H100 (NVIDIA's OpenCL driver): install the carried wheels, point the
# ICD loader at the driver, then run the benchmarks named on the command line.
#
#   bash deploy/h100.sh bench [EXTRA ARGS...]     # drape bench on the GPU
#   bash deploy/h100.sh tune                      # work-group sizes for the 'many' workload
#   bash deploy/h100.sh tradeoff [ARGS]           # speed against accuracy
#   bash deploy/h100.sh loadtest [ARGS]           # the load-test table (below); ARGS override it
#   bash deploy/h100.sh scaleout [ARGS]           # one server's knee against SO_SERVERS servers' (below)
#   bash deploy/h100.sh serve [ARGS]              # drape serve itself (e.g. --workers 2 --device gpu:0,gpu:1)
#   bash deploy/h100.sh devices                   # the device check on the GPU and on the wheel's CPU PoCL
#   bash deploy/h100.sh latency [ARGS]            # input latency with the pipeline on and off
#   bash deploy/h100.sh tool NAME [ARGS]          # python -m drape.server.tools.NAME (encodebench, penetration...)
#
# The load-test table: 16 client processes, 32x32 cloths with bending, 10 iterations, bundles,
# loads of 128 .. 4096 cloths in float32 and 4096 in quant16, one server (admission off: the raw
# capacity), LT_SECONDS (default 20) measured seconds each so the whole table stays under
# 9 minutes; one JSON, a markdown table, the summary plot and the largest load's plots.
# LT_OFFERED=2048 adds a run offering twice 2048 cloths to a server with admission on.
#
# The scale-out figure (issue 11): SO_SERVERS (default 2) drape serve processes sharing the GPU
# (each its own OpenCL context, server id and port, peers on loopback), SO_CLIENTS (default 8)
# client processes placing their cloths by the servers' published load; the knee of one server,
# then of SO_SERVERS, from SO_START (default 64) cloths, doubling, then 2 halvings; SO_SECONDS
# (default 5) measured seconds a load; stops starting loads after 420 s (under ~8 minutes).
# SO_ROUTER=1: the servers and clients behind one Zenoh router process instead. SO_DEVICES: the
# servers' devices in turn (gpu:0,gpu:1 on the 2-GPU H200 machine: one server per GPU).
#
# Results land in $OUT (the device tool's folder) or out/h100. Wheels come from .whl/ (see
# docs/benchmarks.md for the pip download line that fills it).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-out/h100}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ ! -f /tmp/site/.wheels-installed ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    touch /tmp/site/.wheels-installed
fi
# the project itself is reinstalled every call: the working tree may have changed
python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir --upgrade --target /tmp/drape-site .
export PYTHONPATH=/tmp/drape-site:/tmp/site
mkdir -p /tmp/icd
echo /usr/local/nvidia/lib64/libnvidia-opencl.so.1 > /tmp/icd/nvidia.icd
export OCL_ICD_VENDORS=/tmp/icd
export DRAPE_DEVICE=${DRAPE_DEVICE:-gpu}
drape() { python3 -m drape.server.cli "$@"; }
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
nproc
drape devices
what=${1:-bench}
shift || true
case "$what" in
    bench)
        drape bench --json "$OUT/bench-h100.json" --markdown "$OUT/bench-h100.md" "$@" 2>&1 | tee "$OUT/bench-h100.txt" ;;
    tune)
        # register cap x unroll for the global-memory path (seed), unroll for the local path (many)
        for regs in ${TUNE_REGS:-0 64 32}; do for u in ${TUNE_UNROLL:-1 2 4 8}; do
            echo "== DRAPE_NV_MAXRREG=$regs DRAPE_LINK_UNROLL_GLOBAL=$u DRAPE_LINK_UNROLL_LOCAL=$u"
            DRAPE_NV_MAXRREG=$regs DRAPE_LINK_UNROLL_GLOBAL=$u DRAPE_LINK_UNROLL_LOCAL=$u \
                drape bench seed many --solvers workgroup --counts 4096 --frames 20 "$@" 2>&1 | grep -E "^(seed|many) "
        done; done 2>&1 | tee "$OUT/tune-h100.txt" ;;
    tradeoff)
        drape tradeoff --json "$OUT/tradeoff-h100.json" --out "$OUT" "$@" 2>&1 | tee "$OUT/tradeoff-h100.txt" ;;
    loadtest)
        drape loadtest --clients 16 --size 32 --iterations 10 --bundle --no-admission \
            --loads 128,256,512,1024,2048,4096,4096:quant16 --seconds "${LT_SECONDS:-20}" --max-total-seconds 480 \
            --quiet --json "$OUT/loadtest-h100.json" --markdown "$OUT/loadtest-h100.md" --out /tmp/lt-plots "$@" \
            2>&1 | grep -v " INFO drape.server.service" | tee "$OUT/loadtest-h100.txt"
        # the summary plot and the plots of the last load run (the rest stay on the machine)
        cp /tmp/lt-plots/loadtest-summary.png "$OUT/" 2>/dev/null || true
        for f in $(ls -t /tmp/lt-plots/loadtest-[0-9]*.png | head -2); do cp "$f" "$OUT/"; done
        # LT_OFFERED=N: then offer twice N cloths to a server with admission on (past the knee):
        # admitted against refused submits and the admitted cloths' figures (about a minute more)
        if [[ -n "${LT_OFFERED:-}" ]]; then
            drape loadtest --clients 16 --size 32 --iterations 10 --bundle --admission --loads "$LT_OFFERED" \
                --offered 2 --seconds 10 --quiet --json "$OUT/loadtest-h100-offered.json" \
                --markdown "$OUT/loadtest-h100-offered.md" --out /tmp/lt-offered 2>&1 \
                | grep -v " INFO drape.server.service" | tee "$OUT/loadtest-h100-offered.txt"
        fi ;;
    scaleout)
        drape loadtest --scale-out --servers "${SO_SERVERS:-2}" ${SO_ROUTER:+--router} ${SO_DEVICES:+--device "$SO_DEVICES"} \
            --clients "${SO_CLIENTS:-8}" \
            --size 32 --iterations 10 --bundle --no-admission --loads "${SO_START:-64}" --seconds "${SO_SECONDS:-5}" \
            --bisect 2 --max-total-seconds 420 --quiet --json "$OUT/scaleout-h100.json" \
            --markdown "$OUT/scaleout-h100.md" --out /tmp/so-plots "$@" 2>&1 \
            | grep -v " INFO drape.server.service" | tee "$OUT/scaleout-h100.txt"
        cp /tmp/so-plots/loadtest-summary.png "$OUT/scaleout-summary.png" 2>/dev/null || true ;;
    serve)
        exec python3 -m drape.server.cli serve "$@" ;;
    latency)
        python3 -m drape.server.tools.latencybench --json "$OUT/latency-h100.json" "$@" 2>&1 \
            | grep -v "INFO" | tee "$OUT/latency-h100.txt" ;;
    tool)
        name=$1; shift
        python3 -m "drape.server.tools.$name" "$@" 2>&1 | grep -v " INFO " | tee "$OUT/$name-h100.txt" ;;
    devices)
        # the device check (server/sim/opencl/devicecheck.py) afresh on every device: NVIDIA's and
        # the CPU PoCL inside the pyopencl wheel (LLVM 14) on this host's CPU
        lscpu | grep -E "^(Model name|CPU\(s\)):"
        echo "AVX-512: $(grep -c -m1 avx512f /proc/cpuinfo || true)"
        pocl=$(find /tmp/site -name "libpocl*.so*" | head -1)
        if [[ -n "$pocl" ]]; then echo "$pocl" > /tmp/icd/pocl.icd; else echo "no PoCL in the wheels"; fi
        DRAPE_DEVICE=auto drape devices --check 2>&1 | tee "$OUT/devices-h100.txt" ;;
    *)
        echo "unknown: $what" >&2; exit 2 ;;
esac
