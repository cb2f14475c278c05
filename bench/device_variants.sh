#!/usr/bin/env bash
# bench/variants.py over whole suites on a lent GPU machine: one case per process (one CPU thread each),
# the GPU shared, every variant beside the unchanged `fast` preset in the same process (CUDA draws differ
# between runs, so compare only within one). Logs of all cases end up in $OUT/all.log (the device tool
# brings back at most 8 files). Written for this project's device machine, whose python3 holds a CUDA
# torch but not pynrrd, nibabel, pydicom, imageio, tifffile, tqdm (carry them as wheels in .whl/) nor vtk
# (so not the 721a suite, whose centreline is read with vtk).
#
#   VARIANTS_FILE=variants.txt bash bench/device_variants.sh     # one JSON object of setting overrides per line
#   SUITES='rca lad' CASES='0 1 … 9' P=20 DEADLINE=500 PROTOCOL=realistic-static-lao30-rao30 CUDA_TESTS='Testing/test_projector.py -k cuda'
set -u
t0=$SECONDS
out=${OUT:-device-variants}
mkdir -p "$out" /tmp/device-variants
logs=/tmp/device-variants
if ls .whl/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl 2>&1 | tail -2
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
{ nvidia-smi -L; nproc; python3 -c 'import torch, numpy; print("torch", torch.__version__, torch.cuda.get_device_name(0), "numpy", numpy.__version__)'; } > $logs/00-machine.log 2>&1
if [ -n "${CUDA_TESTS:-}" ]; then
    timeout 120 python3 -m pytest -q -p no:cacheprovider $CUDA_TESTS > $logs/01-cuda-tests.log 2>&1
    echo "cuda tests exit $? after $((SECONDS - t0)) s" >> $logs/01-cuda-tests.log
fi
export VARIANTS_FILE=${VARIANTS_FILE:?one JSON object per line} PROTOCOL=${PROTOCOL:-realistic-static-lao30-rao30} LOGS=$logs
left=$(( ${DEADLINE:-500} - (SECONDS - t0) ))
# all cases at once (P ≥ their number) end their variants together if the deadline stops them: balanced rows
for s in ${SUITES:-rca lad}; do for c in ${CASES:-0 1 2 3 4 5 6 7 8 9}; do echo "$s $c"; done; done \
  | timeout "$left" xargs -P "${P:-20}" -L 1 bash -c 'mapfile -t v < "$VARIANTS_FILE"; python3 bench/variants.py --suite $1 --case $2 --protocol $PROTOCOL --threads 1 "${v[@]}" > "$LOGS/v-$1-$2.log" 2>&1' _
echo "runs ended after $((SECONDS - t0)) s" >> $logs/00-machine.log
cat $logs/*.log > "$out/all.log"
