#!/usr/bin/env bash
# The reference solvers' environments (never dependencies of sdp), under .venv-anchors/:
#   croc/      crocoddyl 3.2.1 (Python) with pin 4.0.0, and sdp itself: bench/crocoddyl_compare.py runs here
#   aligator/  libaligator 0.19.1 (aligator's C++ library, no Python bindings) with libpinocchio 4.1.0, Eigen and
#              urdfdom headers; bench/anchors/proxddp_solve.cpp is built against it into bench/anchors/build/
#
#   bash bench/anchors/setup.sh        # about 4 minutes on a new machine (pip 2.5, the C++ build 1), 3.3 GB
#
# Why two: crocoddyl 3.2.1's wheels are built against libpinocchio 4.0.0 (with pin 4.1 they load but crash,
# docs/benchmarks.md), and libaligator 0.19.1's against libpinocchio 4.1.0: installed beside pin 4.0.0 (which
# pip allows: libaligator asks for libpinocchio unpinned) it links, then aborts with std::bad_alloc copying a
# pinocchio Model in MultibodyFreeFwdDynamics (the Model's layout changed between 4.0 and 4.1).
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=${SDP_ANCHORS_ENV:-.venv-anchors}
mkdir -p "$ROOT"
python3 -m venv "$ROOT/croc"
"$ROOT/croc/bin/pip" install -q torch==2.13.0 crocoddyl==3.2.1 pin==4.0.0
"$ROOT/croc/bin/pip" install -q -e . 'pin==4.0.0'
python3 -m venv "$ROOT/aligator"
"$ROOT/aligator/bin/pip" install -q libaligator==0.19.1 'libpinocchio==4.1.0' cmeel-eigen cmeel-urdfdom-headers
PREFIX=$(ls -d "$PWD/$ROOT"/aligator/lib/python3*/site-packages/cmeel.prefix)
cmake -S bench/anchors -B bench/anchors/build -DCMAKE_PREFIX_PATH="$PREFIX" -DCMAKE_BUILD_TYPE=Release >/dev/null
cmake --build bench/anchors/build -j 2
echo "anchors ready: $ROOT/croc (crocoddyl 3.2.1, pin 4.0.0), $ROOT/aligator (libaligator 0.19.1, libpinocchio 4.1.0), bench/anchors/build/proxddp_solve"
