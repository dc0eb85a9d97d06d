#!/bin/bash
# A GPU machine's check (session 42), for a machine with the CUDA torch and no registry: the project's other wheels
# in .whl, the GL loaders' .deb files in .gl and a warm cache in .svcache (all beside this repository's root);
# results in $OUT.
# Two DAgger runs at once, each collecting and validating in J spawned jobs (train --jobs) with the fit on CUDA:
# av-nav on AudioGoal (member 1's recipe, more frames) and av-nav on SemanticAudioNav (the shipped recipe, more
# frames). Their logs, stderr and best.pt are copied to $OUT as they go, so a run stopped at its limit still returns
# what it reached. The tree must stay under the tool's 64 MiB: untrack agents/checkpoints/*.pt (none is needed here)
# for the call and ignore them in .git/info/exclude; restore both afterwards.
# Usage: SV_LENT_MACHINE=1 scripts/device/dagger_scale.sh FRAMES ITERATIONS JOBS VAL_EPISODES LIMIT_S (session 42: 120000 6 7 21 470)
cd "$(dirname "$0")/../.."
F=${1:-120000} IT=${2:-6} J=${3:-7} V=${4:-21} LIM=${5:-470}
. scripts/device/lent.sh .svcache
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; nproc
python3 -c "import sys, torch; print(sys.version.split()[0], torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"
T0=$SECONDS
timeout $LIM python3 -m app.cli train --agent av-nav --task AudioGoal --frames $F --iterations $IT --val-episodes $V \
  --learner drawn --jobs $J --dataset-frames $((F + 8000)) --device cuda --seed 0 --out /tmp/ag > /tmp/ag.out 2> /tmp/ag.err &
PA=$!
timeout $LIM python3 -m app.cli train --agent av-nav --task SemanticAudioNav --frames $F --iterations $IT --val-episodes $V \
  --jobs $J --dataset-frames $((F + 8000)) --device cuda --seed 0 --out /tmp/san > /tmp/san.out 2> /tmp/san.err &
PS=$!
copy() {
  for r in ag san; do
    cp /tmp/$r/log.csv $OUT/${r}_log.csv 2>/dev/null; cp /tmp/$r.err $OUT/${r}.err 2>/dev/null
    [ -f /tmp/$r/best.pt ] && cp /tmp/$r/best.pt $OUT/${r}_best.tmp && mv $OUT/${r}_best.tmp $OUT/${r}_best.pt
  done
}
while kill -0 $PA 2>/dev/null || kill -0 $PS 2>/dev/null; do
  sleep 10; copy
  echo "t $((SECONDS - T0)) s: ag $(tail -1 /tmp/ag.err 2>/dev/null | cut -c1-160)"; echo "   san $(tail -1 /tmp/san.err 2>/dev/null | cut -c1-160)"
done
wait $PA; echo "ag rc $?"; wait $PS; echo "san rc $?"
copy; echo "done at $((SECONDS - T0)) s"; ls -la $OUT
