#!/usr/bin/env bash
# GPU session 1 (device tool, H100/H200): import check, env and trainer throughput at GPU
# sizes, the CPU test suite, then the long runs: the `paper` preset (3 seeds to 3e6
# transitions) and the full MuJoCo protocol (1M steps, four tasks, T-TD3 and TD3, 3 seeds;
# experiments/mujoco_compare.py). Run from the repo root with brax/mujoco wheels in .whl/ (see
# docs/performance.md). Writes everything to $OUT. tests/test_gpu_session.py checks that every
# module, script and flag named here exists (CPU, no GPU needed).
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
python3 -c "import sys, jax; print(sys.version.split()[0], 'jax', jax.__version__, jax.devices())"
python3 -c "import ttd3_jax.train, ttd3_jax.sim.env, ttd3_jax.evaluate, ttd3_jax.control.nmpc, ttd3_jax.run.sharding, brax.envs; print('imports ok')" 2>&1 | tail -1
echo "== env throughput"
timeout 120 python3 benchmarks/env_throughput.py --ablate --env-last --out $OUT/env_gpu.jsonl 2>&1 | grep -v Warning  # issue 2's ratio at 1024 envs
timeout 150 python3 benchmarks/env_throughput.py --envs 100000 --steps 1000 --repeats 3 --out $OUT/env_gpu.jsonl 2>&1 | grep -v Warning
echo "== trainer throughput"
timeout 200 python3 benchmarks/trainer_throughput.py --large --repeats 2 --out $OUT/trainer_gpu.jsonl 2>&1 | grep -v Warning
timeout 200 python3 benchmarks/trainer_throughput.py --only paper --repeats 2 --out $OUT/trainer_gpu.jsonl 2>&1 | grep -v Warning
echo "== CPU tests (jax $(python3 -c 'import jax; print(jax.__version__)'))"
JAX_PLATFORMS=cpu timeout 600 python3 -m pytest -q -n 6 -p no:cacheprovider tests > $OUT/pytest_cpu.log 2>&1
echo "pytest rc $?" >> $OUT/pytest_cpu.log
tail -5 $OUT/pytest_cpu.log
echo "== long runs: the paper preset (3 seeds, 3e6 transitions) and the MuJoCo protocol, side by side"
python3 -m ttd3_jax.train --preset paper --num-seeds 3 --total-transitions 3000000 --out $OUT/runs \
  > $OUT/paper_run.log 2>&1 &
python3 experiments/mujoco_compare.py --parallel 8 --out $OUT/mujoco --device-note "GPU session 1" \
  > $OUT/mujoco.log 2>&1
wait
tail -5 $OUT/paper_run.log $OUT/mujoco.log
