#!/bin/bash
# Every case of make_cases.py (or those named) under the default CLI plus OVERRIDES: ATE in mm per case into $BENCH/LABEL/summary.txt.
# Box cases run with region=object; the *rig* ones are given their depth camera; 7-Scenes its first 300 frames.
# usage: bench.sh REPO LABEL "CASES" [overrides...]  -> ${BENCH:-/tmp/bench}/LABEL/CASE.ate (mm), 2 parallel runs, 1 thread each
REPO=$1; LABEL=$2; LIST=$3; shift 3
ROOT=${CASES:-/tmp/cases}  # the cases' folder (make_cases.py's CASES)
OUT=${BENCH:-/tmp/bench}/$LABEL; mkdir -p $OUT
run() {
  c=$1; shift
  extra=""
  case $c in boxclean*rig*|boxkinectrig*) extra="region=object data.depth_intrinsics=[600,600,320,240] data.T_color_depth=[[1,0,0,-0.1],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";; box*) extra="region=object";; 7scenes*) extra="data.max_frames=300";; esac
  cd /tmp && OMP_NUM_THREADS=1 PYTHONPATH=$REPO ${PYTHON:-python} -m torchtrack.cli data=tum data.root=$ROOT/$c plots=false hydra.run.dir=$OUT/$c $extra "$@" > $OUT/$c.log 2>&1
  tail -c 400 $OUT/$c.log | grep -o "ate_rmse_m=[0-9.e-]*" | sed 's/ate_rmse_m=//' | awk '{printf "%.3f\n", $1*1000}' > $OUT/$c.ate
}
export -f run; export OUT REPO ROOT PYTHON
printf "%s\n" $LIST | xargs -P 2 -I{} bash -c 'run {} "$@"' _ "$@"
for c in $LIST; do printf "%s %s\n" $c "$(cat $OUT/$c.ate)"; done > $OUT/summary.txt
