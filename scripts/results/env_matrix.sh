#!/usr/bin/env bash
# The environment matrix: does the same commit give the same verdict under every torch the
# project supports and on other CPUs? For each torch/torchvision pair, a fresh venv (the
# locked one from configs/constraints.txt; any other with the lock's non-torch pins and the
# pip cap lifted), then for each CPU variant the demo, the two `check`s against
# results/baselines/ and pytest. CPU variants stand for other machines: the native kernels,
# oneDNN held one instruction set lower (AVX-512 -> AVX2, AVX2 -> SSE41) and ATen's
# vectorised kernels off (ATEN_CPU_CAPABILITY=default); 1 thread instead of 2 for the demo.
#
#   bash scripts/results/env_matrix.sh [OUT_DIR]                 (default runs/env_matrix)
#   TORCH_PAIRS="2.14.1/0.29.1 2.15.0/0.29.2" PYTEST_ARGS="-q tests/matching/test_parity.py" bash scripts/results/env_matrix.sh
#   VARIANTS="native avx2" ...   (names below; default: all that apply to this CPU)
#
# Appends to OUT_DIR/matrix.md (torch, variant, check verdict, pytest counts, minutes) and keeps
# each cell's demo under OUT_DIR/<torch>/<variant>/demo, from which
# `python scripts/results/demo_spread.py --matrix OUT_DIR` derives check's tolerances. Venvs are kept
# (OUT_DIR/venv-<torch>, about 6 GB each) and reused; delete them when done.
set -uo pipefail
cd "$(dirname "$0")/../.."
repo="$PWD"
out="$(realpath -m "${1:-runs/env_matrix}")"
mkdir -p "$out"
pairs="${TORCH_PAIRS:-2.14.1/0.29.1 2.15.0/0.29.2}"
locked_torch="$(sed -n 's/^torch==//p' configs/constraints.txt)"
pytest_args="${PYTEST_ARGS:--q}"

if grep -q avx512f /proc/cpuinfo; then lower_isa=AVX2; elif grep -q avx2 /proc/cpuinfo; then lower_isa=SSE41; else lower_isa=""; fi
all_variants="native threads1 aten-default"
[ -n "$lower_isa" ] && all_variants="native threads1 onednn-${lower_isa,,} aten-default"
variants="${VARIANTS:-$all_variants}"

variant_env() {  # the environment variables of a variant
  case "$1" in
    native) echo "OMP_NUM_THREADS=2" ;;
    threads1) echo "OMP_NUM_THREADS=1" ;;
    onednn-*) echo "OMP_NUM_THREADS=2 ONEDNN_MAX_CPU_ISA=${1#onednn-}" ;;
    aten-default) echo "OMP_NUM_THREADS=2 ATEN_CPU_CAPABILITY=default" ;;
    *) echo "unknown variant $1" >&2; return 1 ;;
  esac
}

make_venv() {  # $1 torch, $2 torchvision -> venv path on stdout
  local venv="$out/venv-$1"
  if [ ! -x "$venv/bin/e3cm-bench" ]; then
    python3 -m venv "$venv" >&2
    "$venv/bin/python" -m pip install -q --upgrade pip >&2
    if [ "$1" = "$locked_torch" ]; then
      "$venv/bin/python" -m pip install -q -c configs/constraints.txt -e ".[test]" >&2
    else  # the lock without torch and what comes with it; the machine's cap lifted for this one
      grep -v -E '^(torch|torchvision|triton|nvidia-|cuda-)' configs/constraints.txt > "$out/constraints-$1.txt"
      PIP_CONSTRAINT=/dev/null "$venv/bin/python" -m pip install -q -c "$out/constraints-$1.txt" \
        "torch==$1" "torchvision==$2" -e ".[test]" >&2
    fi
  fi
  echo "$venv"
}

table="$out/matrix.md"  # rows are appended: run the script several times for several cells
if [ ! -f "$table" ]; then
  echo "| torch / torchvision | variant | demo check | pytest ($pytest_args unless said) | minutes |" > "$table"
  echo "|---|---|---|---|---:|" >> "$table"
fi
for pair in $pairs; do
  torch_v="${pair%/*}"; vision_v="${pair#*/}"
  venv="$(make_venv "$torch_v" "$vision_v")" || { echo "| $pair | - | venv failed | - | - |" >> "$table"; continue; }
  installed="$("$venv/bin/python" -c 'import torch, torchvision; print(torch.__version__, "/", torchvision.__version__)')"
  for variant in $variants; do
    cell="$out/$torch_v/$variant"
    mkdir -p "$cell"
    env_vars="$(variant_env "$variant")" || exit 2
    start=$(date +%s)
    echo "== torch $installed, $variant ($env_vars)"
    # shellcheck disable=SC2086
    (cd "$repo" && env $env_vars "$venv/bin/e3cm-bench" demo --out "$cell/demo") > "$cell/demo.log" 2>&1
    verdict="pass"
    for set_name in hpatches scenes; do
      # shellcheck disable=SC2086
      env $env_vars "$venv/bin/e3cm-bench" check "$cell/demo/$set_name" --baseline "results/baselines/demo_$set_name.csv" \
        --tolerances results/baselines/demo_tolerances.csv >> "$cell/check.log" 2>&1 || verdict="FAIL"
    done
    tests="-"
    if [ "$variant" != threads1 ]; then  # pytest under each kernel set; the thread count only for the demo
      # shellcheck disable=SC2086
      env $env_vars "$venv/bin/python" -m pytest $pytest_args -p no:cacheprovider > "$cell/pytest.log" 2>&1
      tests="$(grep -E '^=*.*(passed|failed|error).* in [0-9.]+s' "$cell/pytest.log" | tail -1 | sed 's/=//g; s/^ *//; s/ *$//')"
    fi
    minutes=$(( ($(date +%s) - start + 30) / 60 ))
    [ "$tests" != "-" ] && tests="${tests:-no summary} (pytest $pytest_args)"
    echo "| $installed | $variant | $verdict | $tests | $minutes |" | tee -a "$table"
  done
done
echo "matrix: $table"
