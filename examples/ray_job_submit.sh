#!/usr/bin/env bash
# Submit a data run to a running Ray cluster with Ray Jobs.
#
#   RAY_ADDRESS=http://HEAD:8265 bash examples/ray_job_submit.sh NAME [CONFIG]
#
# RUN_DIR (default /shared/runs/NAME) names another run directory; CONFIG may be a path inside
# this repository (uploaded with the job) or an absolute path every node can read.
# - Every node needs the same environment (this package and its dependencies, e.g. the same
#   virtualenv or container image): stage fingerprints include the package version, so mixed
#   versions would be refused on resume.
# - The run directory must be on storage every node mounts (here /shared): actors on any node
#   write their outputs there, and the driver writes the manifests there.
# - The working directory (this repository) is uploaded with the job; its configs/ is what the
#   entrypoint reads. Large local folders are excluded from the upload.
# - Submitting the same NAME again resumes the run: done items are kept, the rest is redone.
# - Ray 2.5x clusters use token authentication: give this shell the cluster's token too
#   (RAY_AUTH_MODE=token and RAY_AUTH_TOKEN, or RAY_AUTH_TOKEN_PATH).
set -euo pipefail

NAME=${1:?usage: ray_job_submit.sh NAME [CONFIG]}
CONFIG=${2:-configs/full.yaml}
RUN_DIR=${RUN_DIR:-/shared/runs/$NAME}
: "${RAY_ADDRESS:?set RAY_ADDRESS to the Ray dashboard of the cluster, e.g. http://HEAD:8265}"
cd "$(dirname "$0")/.."

anchordp3 config validate "$CONFIG"       # refuse a bad config before anything is submitted

ray job submit \
  --address "$RAY_ADDRESS" \
  --submission-id "anchordp3-$NAME-$(date +%Y%m%d-%H%M%S)" \
  --working-dir . \
  --runtime-env-json '{"excludes": [".git", ".venv", "runs", "benchmarks/out"]}' \
  -- anchordp3 run "$CONFIG" --run-dir "$RUN_DIR" --address auto

# After the job: check every output against its checksum (exit 1 names what is missing or
# corrupt); `anchordp3 verify --repair` redoes exactly those items.
#   anchordp3 status "$RUN_DIR"
#   anchordp3 verify "$RUN_DIR"
