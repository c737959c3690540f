#!/usr/bin/env bash
# A data run on a Slurm allocation: a Ray head on the first node, Ray workers on the others,
# then the driver on the head node joins that cluster with --address auto.
#
#   sbatch --export=ALL,NAME=full-v1 examples/slurm_batch.sh
#
# Requirements: the repository and its .venv on storage every node mounts (or the same
# environment installed on each node), and RUN_DIR on shared storage. Resubmitting with the same
# NAME resumes the run.
#
# Settings (environment, e.g. --export=ALL,NAME=x,CONFIG=y): NAME, CONFIG, RUN_DIR, REPO (the
# repository, default the submit folder), RAY_PORT, RAY_CPUS (logical CPUs per node, default
# the allocation's), HEAD_IP (the address Ray binds on the head, default the head's first
# address; 127.0.0.1 on a single host), RAY_TMPDIR (Ray's folder for sockets and logs, default /tmp).
#SBATCH --job-name=anchordp3
#SBATCH --nodes=4
#SBATCH --ntasks-per-node=1
#SBATCH --exclusive
#SBATCH --time=24:00:00
#SBATCH --output=%x-%j.out
##SBATCH --gpus-per-node=1            # uncomment on GPU nodes: render actors then share the GPUs

set -euo pipefail

NAME=${NAME:-full}
CONFIG=${CONFIG:-configs/full.yaml}
RUN_DIR=${RUN_DIR:-/shared/runs/$NAME}
REPO=${REPO:-$SLURM_SUBMIT_DIR}
BIN=$REPO/.venv/bin
PORT=${RAY_PORT:-6379}
CPUS=${RAY_CPUS:-${SLURM_CPUS_ON_NODE:-$(nproc)}}

cd "$REPO"
"$BIN/anchordp3" config validate "$CONFIG"   # a bad config fails here, before any node is touched

mapfile -t NODES < <(scontrol show hostnames "$SLURM_JOB_NODELIST")
HEAD=${NODES[0]}
HEAD_IP=${HEAD_IP:-$(srun --nodes=1 --ntasks=1 -w "$HEAD" hostname --ip-address | awk '{print $1}')}
ADDRESS=$HEAD_IP:$PORT
echo "ray head: $HEAD ($ADDRESS); workers: ${NODES[*]:1}"

# --block keeps each `ray start` in the foreground of its srun step; the steps end with the job.
srun --nodes=1 --ntasks=1 -w "$HEAD" --overlap \
  "$BIN/ray" start --head --node-ip-address="$HEAD_IP" --port="$PORT" --num-cpus="$CPUS" \
  --include-dashboard=false --block &
sleep 10
for node in "${NODES[@]:1}"; do
  # each worker binds the address named for it: its own, or loopback when the head is on loopback
  if [ "$HEAD_IP" = 127.0.0.1 ]; then NODE_IP=127.0.0.1
  else NODE_IP=$(srun --nodes=1 --ntasks=1 -w "$node" --overlap hostname --ip-address | awk '{print $1}'); fi
  srun --nodes=1 --ntasks=1 -w "$node" --overlap \
    "$BIN/ray" start --address="$ADDRESS" --node-ip-address="$NODE_IP" --num-cpus="$CPUS" --block &
done

# wait until every node has joined (at most 5 minutes)
for _ in $(seq 60); do
  alive=$("$BIN/python" -c 'import ray, sys; ray.init(address=sys.argv[1], logging_level="ERROR"); print(sum(n["Alive"] for n in ray.nodes()))' "$ADDRESS" 2>/dev/null || echo 0)
  [ "$alive" -ge "${#NODES[@]}" ] && break
  sleep 5
done
[ "$alive" -ge "${#NODES[@]}" ] || { echo "only $alive of ${#NODES[@]} Ray nodes joined" >&2; exit 1; }
echo "ray cluster: $alive nodes"

# this batch script runs on the first node, where the head is; the address is named, not "auto",
# so that another Ray on the same machine is never joined
"$BIN/anchordp3" run "$CONFIG" --run-dir "$RUN_DIR" --address "$ADDRESS"
"$BIN/anchordp3" verify "$RUN_DIR"

# stop this job's Ray nodes (their srun steps; `ray stop` would stop every Ray on the machine)
kill $(jobs -p) 2>/dev/null || true
wait || true
