#!/bin/bash
# usage: bench.sh LABEL "CASES" [overrides...]; sequential, one thread. REPO defaults /work/rigwt
REPO=${REPO:-/work/rigwt}; LABEL=$1; LIST=$2; shift 2
OUT=/tmp/rigbench/$LABEL; mkdir -p $OUT
for c in $LIST; do
  extra="region=object"
  case $c in *rig*) extra="region=object data.depth_intrinsics=[600,600,320,240] data.T_color_depth=[[1,0,0,-0.1],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";; esac
  orc=""; if [ -n "$ORACLE" ]; then case $c in boxcleanrig*) s=${c#boxcleanrig}; orc="TT_ORACLE_DEPTH=/tmp/cases/boxclean${s:0:1} TT_ORACLE_USE=$ORACLE";; esac; fi
  (cd /tmp && flock /tmp/rigbench/lock env $orc OMP_NUM_THREADS=1 PYTHONPATH=$REPO /work/main/.venv/bin/python -m torchtrack.cli data=tum data.root=/tmp/rigcases/$c plots=false hydra.run.dir=$OUT/$c $extra "$@" > $OUT/$c.log 2>&1)
  a=$(tail -c 400 $OUT/$c.log | grep -o "ate_rmse_m=[0-9.e-]*" | sed 's/ate_rmse_m=//' | awk '{printf "%.3f\n", $1*1000}')
  echo "$c $a" | tee -a $OUT/summary.txt
done
