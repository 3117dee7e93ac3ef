#!/bin/bash
# One line per run: the newest curve point (env_steps, updates, rolling success) and the last validation.
for d in /tmp/r/*/; do
  n=$(basename $d); j=$(ls -d $d/jobs/*-ego-idm 2>/dev/null | head -1)
  c=$( [ -n "$j" ] && tail -1 $j/curve.csv 2>/dev/null | cut -d, -f1-4)
  v=$( [ -n "$j" ] && tail -1 $j/validation.csv 2>/dev/null)
  done_=$(grep -c '"job_dir"\|artifacts\|succeeded' /tmp/r/$n.log 2>/dev/null)
  echo "$n curve=[$c] val=[$v] policy=$( [ -n "$j" ] && [ -f $j/policy.bpk ] && echo yes || echo no)"
done
