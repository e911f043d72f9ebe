#!/usr/bin/env bash
# The GPU path, measured (issue #16): on a machine with CUDA, the optimisation step at 5k / 20k / 50k cage
# tets and the whole ring (mesh to G-code) with --device cuda, for the default and the paper network; the
# figures go to benchmarks/results/device_ring.json (and the step rows into bench_neural.json, steps_cuda).
#
#   benchmarks/device_ring.sh [--ring PATH] [--device cuda|cpu] [--out DIR] [--dry-run]
#
# --dry-run: a few steps only (5k tets, 3 steps, ring slices with --max-steps 5), to check the script end to
# end on any machine (the CPU dry run is what runs where no GPU is lent). Installs with `make install` when
# the venv is missing (needs PyPI; on a CUDA machine PyPI's torch wheel is a CUDA build).
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
cd "$repo"
ring="$repo/neuralslicer/data/ring.tet"
device=cuda
out="${TMPDIR:-/tmp}/neuralslicer-device-ring"
dry=0
while [ $# -gt 0 ]; do
  case "$1" in
    --ring) ring="$2"; shift 2 ;;
    --device) device="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --dry-run) dry=1; shift ;;
    *) echo "device_ring.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
[ -f "$ring" ] || { echo "device_ring.sh: $ring: no such file (give --ring PATH)" >&2; exit 2; }
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || make install
"$PY" - "$device" <<'EOF'
import sys, torch
dev = sys.argv[1]
print(f"torch {torch.__version__}, cuda available: {torch.cuda.is_available()}"
      + (f", {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""))
if dev.startswith("cuda") and not torch.cuda.is_available():
    sys.exit("device_ring.sh: --device cuda but torch sees no CUDA device (use --device cpu for a dry run)")
EOF
export PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1 PREFECT_HOME="$out/prefect-home"
mkdir -p "$out"
if [ "$dry" = 1 ]; then sizes=5k; steps=3; max_steps=(--max-steps 5); save=(--no-save)
else sizes=5k,20k,50k; steps=20; max_steps=(); save=(); fi

echo "== optimisation step, $sizes cage tets, default and paper networks, $device"
"$PY" benchmarks/bench_neural.py steps --sizes "$sizes" --networks default,paper --steps "$steps" --device "$device" "${save[@]}"

for net in default paper; do
  echo "== ring, $net network, $device"
  rm -rf "$out/ring_$net"
  start=$(date +%s.%N)
  "$PY" -m cli slice "$ring" --up y --out "$out/ring_$net" --device "$device" --network "$net" "${max_steps[@]}" \
    > "$out/ring_$net.log" 2>&1 || { echo "ring ($net) failed, see $out/ring_$net.log" >&2; tail -5 "$out/ring_$net.log" >&2; }
  end=$(date +%s.%N)
  echo "$start $end" > "$out/ring_$net.wall"
done

"$PY" - "$out" "$device" "$dry" <<'EOF'
import json, sys, time
from pathlib import Path
out, device, dry = Path(sys.argv[1]), sys.argv[2], sys.argv[3] == "1"
rows = []
for net in ("default", "paper"):
    d = out / f"ring_{net}"
    start, end = (float(t) for t in (out / f"ring_{net}.wall").read_text().split())
    row = {"network": net, "device": device, "whole_run_s": round(end - start, 1), "completed": (d / "metrics.json").is_file()}
    if row["completed"]:
        m = json.loads((d / "metrics.json").read_text())
        row.update({k: m.get(k) for k in ("field.steps", "wall_s.field", "wall_s.toolpaths", "sf.overhang_area_fraction",
                                          "sf.overhang_area_fraction_planar", "collisions", "n_layers",
                                          "provenance.device.torch_device", "provenance.device.cuda_name")})
    rows.append(row)
    print(json.dumps(row))
result = {"recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "dry_run": dry, "ring": rows,
          "paper": {"rtx4080_optimisation_s": 73.4, "rtx4080_end_to_end_s": 124.5}}
path = Path("benchmarks/results") / ("device_ring_dry_run.json" if dry else "device_ring.json")
path.write_text(json.dumps(result, indent=2))
print(f"figures: {path}")
EOF
