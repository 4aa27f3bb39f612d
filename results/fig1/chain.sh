#!/usr/bin/env bash
# Issue 82 step 1: one single-worker chain per method over fig1's quadrotor-0 dataset sizes, seeds 0-4 in one stack
# per size; resumable (each stack from its last checkpoint). Usage, from the project root with the venv active:
#   bash results/fig1/chain.sh sdp runs/fig1q 8 16 32
#   bash results/fig1/chain.sh dp runs/fig1q-b 16 32
set -euo pipefail
method=$1; out=$2; shift 2
for n in "$@"; do
  only=$(for s in 0 1 2 3 4; do printf 'quadrotor-0-%s-n%s-s%s,' "$method" "$n" "$s"; done)
  echo "$(date -u +%FT%TZ) start $method n_traj $n in $out"
  sdp pipeline fig1 --run --out "$out" --workers 1 --only "${only%,}"
  echo "$(date -u +%FT%TZ) done $method n_traj $n"
done
