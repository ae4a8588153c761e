#!/usr/bin/env bash
# Issue 14's control experiment: the supernet trained behind a flat phase (no lens: an open
# aperture) and behind the fixed hyperbolic lens on the same ambiguity pairs (C.3), for three
# training seeds, then V, Dice and slip MSE of N_max and N_min on held-out ambiguity pairs.
# Usage: scripts/flat_vs_hyperbolic.sh OUT_DIR [NANOEYE_BINARY]   (docs/run.md, "Flat vs
# hyperbolic"; about 10 min on 2 cores when idle)
set -euo pipefail
out=${1:?usage: flat_vs_hyperbolic.sh OUT_DIR [NANOEYE_BINARY]}
bin=${2:-target/release/nanoeye}
mkdir -p "$out"
[ -d "$out/train" ] || "$bin" datagen render --set ambiguity --n 40 --seed 0 --width 320 \
  --height 200 --spp 4 --out "$out/train" >/dev/null 2>&1
[ -d "$out/val" ] || "$bin" datagen render --set ambiguity --n 12 --seed 7 --width 320 \
  --height 200 --spp 4 --out "$out/val" >/dev/null 2>&1
printf 'lens\tseed\tV_max\tV_min\tdice_max\tdice_min\tslip_mse_max\tslip_mse_min\tseconds\n'
for seed in 0 1; do
  for lens in flat hyperbolic; do
    run="$out/$lens-$seed"
    "$bin" search train --dataset "$out/train" --val "$out/val" --lens "$lens" --fixed-lens \
      --steps 150 --batch 4 --random-subnets 0 --lr-net 4e-3 --pitch-um 14 \
      --pitch-range-um 12:24 --seed "$seed" --weights-seed "$seed" --out "$run" --json \
      >"$run.json" 2>"$run.err"
    python3 - "$run.json" "$lens" "$seed" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
m = r["max_subnet"]
print("\t".join([sys.argv[2], sys.argv[3]] + ["%.2f" % m["v_deg"], "%.2f" % r["v_deg"],
      "%.3f" % m["dice"], "%.3f" % r["dice"], "%.2f" % m["slip_mse"], "%.2f" % r["slip_mse"],
      "%.0f" % r["seconds"]]))
PY
  done
done
