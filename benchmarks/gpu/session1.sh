#!/usr/bin/env bash
# GPU session 1 (device tool, H100): jax 0.11 / Python 3.12 import check, env and trainer
# throughput at GPU sizes, a MuJoCo timing probe, and the CPU test suite under jax 0.11.
# Run from the repo root with brax/mujoco wheels in .whl/ (see docs/performance.md).
# Writes everything to $OUT.
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
python3 -c "import sys, jax; print(sys.version.split()[0], 'jax', jax.__version__, jax.devices())"
python3 -c "import ttd3_jax.train, ttd3_jax.env, ttd3_jax.evaluate, ttd3_jax.nmpc, ttd3_jax.sharding, brax.envs; print('imports ok')" 2>&1 | tail -1
echo "== env throughput"
timeout 120 python3 benchmarks/env_throughput.py --ablate --env-last --out $OUT/env_gpu.jsonl 2>&1 | grep -v Warning  # issue 2's ratio at 1024 envs
timeout 150 python3 benchmarks/env_throughput.py --envs 100000 --steps 1000 --repeats 3 --out $OUT/env_gpu.jsonl 2>&1 | grep -v Warning
timeout 150 python3 benchmarks/env_throughput.py --envs 1000000 --steps 100 --repeats 3 --out $OUT/env_gpu.jsonl 2>&1 | grep -v Warning
echo "== trainer throughput"
timeout 200 python3 benchmarks/trainer_throughput.py --large --repeats 2 --out $OUT/trainer_gpu.jsonl 2>&1 | grep -v Warning
echo "== mujoco probe + CPU tests (jax $(python3 -c 'import jax; print(jax.__version__)'))"
(JAX_PLATFORMS=cpu timeout 300 python3 -m pytest -q -n 6 -p no:cacheprovider tests > $OUT/pytest_cpu.log 2>&1; echo "pytest rc $?" >> $OUT/pytest_cpu.log) &
timeout 300 python3 experiments/mujoco_compare.py --steps 15000 --warmup 5000 --eval-every 5000 --parallel 8 \
  --out /tmp/mjprobe --device-note "probe" > $OUT/mujoco_probe.log 2>&1
pkill -f mujoco_compare; wait
tail -5 $OUT/pytest_cpu.log
grep -h "compiled\|init + warm\|epoch .*/\|finished" /tmp/mjprobe/logs/*.log | head -60
tar czf $OUT/mjprobe.tgz --exclude=checkpoints -C /tmp mjprobe
