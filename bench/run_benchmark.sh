#!/usr/bin/env bash
# The commands that make the benchmark tables of bench/RESULTS.md (see bench/README.md).
#
#   bench/run_benchmark.sh [quick|rca|lad|721a|clinical|imagecas|all]     (default: all = rca lad 721a)
#
# Environment (all optional):
#   PRESET=fast         optimiser preset (fast | paper)
#   PROTOCOL=paper      simulation protocol of the rca and lad targets (paper | clinical-lao30-rao30 |
#                       clinical-lao50cra25-rao50cra25)
#   CASES=10            cases per procedural suite
#   CASES_721A=3        optimiser seeds on the 721A centreline
#   SEED=0              first case seed
#   SCHEDULER=tcp://…   run on an existing Dask cluster instead of a local one
#   WORKERS=N           local cluster workers (default: cores / THREADS)
#   THREADS=1           torch threads per case
#   EXTRA="--set device=cuda"   more benchmark options (e.g. GPU workers, --steps, --set KEY=VALUE)
#   IMAGECAS=/path/to/labels    folder of ImageCAS label volumes, for the imagecas target
#   OUT=bench/runs      where the result folders go (ignored by git)
#
# Every command resumes: run it again after an interruption and it continues where it stopped.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

PY=${PY:-.venv/bin/python}
PRESET=${PRESET:-fast}
PROTOCOL=${PROTOCOL:-paper}
CASES=${CASES:-10}
SEED=${SEED:-0}
OUT=${OUT:-bench/runs}
MODES=sdfcar,neca,occ-combined,sdf-occ

common=(--preset "$PRESET" --seed "$SEED" --modes "$MODES" --threads-per-worker "${THREADS:-1}")
[[ -n "${SCHEDULER:-}" ]] && common+=(--scheduler "$SCHEDULER")
[[ -n "${WORKERS:-}" ]] && common+=(--workers "$WORKERS")
# shellcheck disable=SC2206  # EXTRA is a list of options on purpose
[[ -n "${EXTRA:-}" ]] && common+=($EXTRA)

bench() {
    echo "+ $PY -m SDFCARLib benchmark $*" >&2
    "$PY" -m SDFCARLib benchmark "$@"
}

run_target() {
    case "$1" in
        quick)  # a smoke test of the harness: 2 tiny cases, 20 steps, about a minute on 2 cores
            bench --suite rca --cases 2 --modes sdfcar,neca --preset fast --steps 20 \
                --volume-shape 48 48 48 --spacing-mm 2 --detector-shape 128 128 --detector-spacing-mm 1 \
                --out "$OUT/quick" ;;
        rca)    # Tables 1 and 3: procedural RCA-like trees (the paper's protocol unless PROTOCOL says)
            bench --suite rca --cases "$CASES" --protocol "$PROTOCOL" "${common[@]}" --out "$OUT/rca-$PRESET-$PROTOCOL" ;;
        lad)    # Tables 2 and 4: procedural LAD-like trees (the paper's protocol unless PROTOCOL says)
            bench --suite lad --cases "$CASES" --protocol "$PROTOCOL" "${common[@]}" --out "$OUT/lad-$PRESET-$PROTOCOL" ;;
        721a)   # the 721A centreline (real anatomy), CASES_721A optimiser seeds (default 3)
            bench --suite 721a --cases "${CASES_721A:-3}" --protocol "$PROTOCOL" "${common[@]}" --out "$OUT/721a-$PRESET-$PROTOCOL" ;;
        clinical)  # binary masks from clinical view pairs instead of line integrals
            for protocol in clinical-lao30-rao30 clinical-lao50cra25-rao50cra25; do
                bench --suite rca --cases "$CASES" --protocol "$protocol" "${common[@]}" --out "$OUT/rca-$PRESET-$protocol"
                bench --suite lad --cases "$CASES" --protocol "$protocol" "${common[@]}" --out "$OUT/lad-$PRESET-$protocol"
            done ;;
        imagecas)  # ImageCAS labels with the DeepCA/NeCA preprocessing (1 mm, 128³, LCA/RCA split)
            if [[ -z "${IMAGECAS:-}" ]]; then
                echo "error: set IMAGECAS to the folder of ImageCAS label volumes (e.g. IMAGECAS=~/ImageCAS/labels)" >&2
                exit 2
            fi
            bench --suite "folder:$IMAGECAS" --protocol paper "${common[@]}" --out "$OUT/imagecas-$PRESET-paper" ;;
        all)
            run_target rca; run_target lad; run_target 721a ;;
        *)
            echo "error: unknown target '$1'; choose quick, rca, lad, 721a, clinical, imagecas or all" >&2
            exit 2 ;;
    esac
}

if [[ $# -eq 0 ]]; then
    set -- all
fi
for target in "$@"; do
    run_target "$target"
done
