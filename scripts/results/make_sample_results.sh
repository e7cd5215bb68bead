#!/usr/bin/env bash
# Regenerates results/sample/: the paper's tables measured on the small real samples in
# ../shared/data (NOT the paper's datasets) with the offline EfficientNet-Lite0 backbone.
# Matches are cached in runs/sample/ (rerunning reuses them); tables, plots and each run's
# summary.csv, per_pair.csv and config.yaml are copied to results/sample/.
#   bash scripts/results/make_sample_results.sh [SHARED_DATA_DIR]
set -euo pipefail
cd "$(dirname "$0")/../.."
data="${1:-../shared/data}"
# Resolutions as in the configs (HPatches full size, pose pairs longer side 1200); no
# difference columns: these are not the paper's datasets, so measured - paper means nothing.
# The peers' rows need their weights (a download this machine cannot make): the built-in methods only.
common=(--backbone efficientnet_lite0 --no-compare --methods sift,dfm,e3cm-release,e3cm,e3cm-ransac,e3cm-plus,direct)

e3cm-bench reproduce table1 --root "$data/hpatches-sequences-release" --out runs/sample/table1_hpatches "${common[@]}"
e3cm-bench reproduce table2 --root "$data/megadepth_test_1500" \
  --scene-info "$data/megadepth_test_1500/scene_info/kitti00_seq.npz" --out runs/sample/table2_kitti "${common[@]}"
e3cm-bench reproduce table3 --root "$data/scannet_sample" \
  --pairs "$data/scannet_sample/pairs_with_gt.txt" --out runs/sample/table3_scannet "${common[@]}"

rm -rf results/sample/table*
for table in table1_hpatches table2_kitti table3_scannet; do
  dest="results/sample/$table"
  mkdir -p "$dest"
  cp runs/sample/$table/table.csv runs/sample/$table/table.md runs/sample/$table/table_*.png "$dest/"
  for run in runs/sample/$table/*/; do
    [ -f "$run/summary.csv" ] || continue  # a run folder (not report/)
    name="$(basename "$run")"
    mkdir -p "$dest/$name"
    cp "$run/summary.csv" "$run/config.yaml" "$run/per_pair.csv" "$dest/$name/"
  done
done
# one paired comparison of two of the runs (docs/results.md, Intervals and paired comparisons)
e3cm-bench compare results/sample/table1_hpatches/sift results/sample/table1_hpatches/e3cm-plus_efficientnet_lite0 \
  --out results/sample/compare/table1_hpatches_sift_vs_e3cm-plus
echo "results/sample/ regenerated"
