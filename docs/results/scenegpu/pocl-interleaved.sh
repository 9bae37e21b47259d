# PoCL, interleaved: "old" is bf06098 (git archive HEAD client kernels server into /tmp/scene_old/src,
# linked as /tmp/scene_old/drape/{client,kernels,server}), "new" the worktree; per line: build,
# median and fastest ms a frame of the scenes kernels (2 scenes of 64 capes, 6 frames), each
# kernel's fastest, the load average. The CPU code path is the same in both (IC_CG 1, no IC_KEPT).
cd /work/wt/scenegpu
for i in 1 2 3 4; do
  for v in old new; do
    if [ $v = old ]; then PP=/tmp/scene_old; else PP=; fi
    PYTHONPATH=$PP .venv/bin/python -c "
from drape.server.tools import scenepass as s
import json,os
r = s.profile(2, 64, 6)
print('$v', r['scenes_ms'], r['scenes_min_ms'], json.dumps(r['kernels_min_ms']), os.getloadavg()[0], flush=True)"
  done
done
