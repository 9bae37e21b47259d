#!/bin/bash
# interleaved: old (349a5dc: 8 passes of hash build + walk, 48 launches) and new, drape bench scenes on PoCL
PY=/work/wt/scenesperf/.venv/bin/python
cd /tmp
for r in 1 2; do
 for S in "4,8" "16,8"; do
  PYTHONPATH=/tmp/oldpkg $PY -m drape.server.cli bench scenes --scenes $S --frames 20 --json /tmp/scb/old-$S-$r.json > /tmp/scb/old-$S-$r.txt 2>&1
  $PY -m drape.server.cli bench scenes --scenes $S --frames 20 --json /tmp/scb/new-$S-$r.json > /tmp/scb/new-$S-$r.txt 2>&1
  PYTHONPATH=/tmp/oldpkg $PY -m drape.server.cli bench scenes --pack-lanes 0 --scenes $S --frames 20 --json /tmp/scb/old-wg-$S-$r.json > /tmp/scb/old-wg-$S-$r.txt 2>&1
  $PY -m drape.server.cli bench scenes --pack-lanes 0 --scenes $S --frames 20 --json /tmp/scb/new-wg-$S-$r.json > /tmp/scb/new-wg-$S-$r.txt 2>&1
 done
done
echo done > /tmp/scb/DONE
