#!/usr/bin/env bash
# The checks a CUDA machine can do that CI cannot (CI has no GPU): the test suite with device "auto"
# choosing the GPU, the sample case on the GPU against its CPU result, and one realistic case timed on
# the GPU and on the same machine's CPU in one run. Written for the device machine this project is
# sometimes lent (its python3 holds a CUDA torch); results go to $OUT (or ./cuda-check) and RESULTS.md.
#
#   bench/cuda_check.sh [WHEEL_DIR]   # WHEEL_DIR: wheels of the packages that python3 lacks
#   STAGES='machine cuda-tests demo suite realistic' DEADLINE=540 WORKERS=12 SUITE_ARGS='--ignore=…' CUDA_TESTS='…'
#
# Each stage has its own time limit, so one that hangs or fails leaves the others' logs.
set -u
out=${OUT:-cuda-check}
mkdir -p "$out"
py=${PYTHON:-python3}
if [ -n "${1:-}" ]; then
    $py -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$1"/*.whl \
        && export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
stages=${STAGES:-machine cuda-tests demo suite realistic}
# failures are written to $out/failures.txt as they happen, so a suite stopped at its limit still names them
mkdir -p /tmp/sdfcar-plugin && cat >/tmp/sdfcar-plugin/live_failures.py <<'PLUGIN'
import os


def pytest_runtest_logreport(report):
    if report.failed:
        with open(os.path.join(os.environ["LIVE_FAILURES_DIR"], "failures.txt"), "a") as log:
            log.write(f"==== {report.nodeid} ({report.when})\n{report.longreprtext}\n")
PLUGIN
export LIVE_FAILURES_DIR=$out PYTHONPATH=$PYTHONPATH:/tmp/sdfcar-plugin
deadline=${DEADLINE:-540}  # seconds for all stages together: a stage gets at most what is left
stage() {  # stage NAME SECONDS COMMAND...: runs COMMAND into $out/NAME.log, prints its tail and time
    local name=$1 limit=$2; shift 2
    [ $((deadline - SECONDS)) -lt "$limit" ] && limit=$((deadline - SECONDS))
    [ "$limit" -lt 5 ] && { echo "== $name: skipped, no time left"; return; }
    case " $stages " in *" $name "*) ;; *) return ;; esac
    local t0=$SECONDS
    timeout "$limit" "$@" >"$out/$name.log" 2>&1
    echo "== $name: exit $? after $((SECONDS - t0)) s (limit $limit s)"
    tail -n "${TAIL:-6}" "$out/$name.log"
}
stage machine 60 bash -c "nvidia-smi -L; nproc; $py -c 'import torch, numpy, scipy, skimage; \
print(\"torch\", torch.__version__, \"cuda\", torch.version.cuda, torch.cuda.is_available(), \
torch.cuda.get_device_name(0) if torch.cuda.is_available() else \"-\", \"numpy\", numpy.__version__)'"
TAIL=8 stage cuda-tests 150 $py -m pytest -q -p no:cacheprovider -p live_failures --tb=short -rs -n 4 ${CUDA_TESTS:-Testing/test_projector.py Testing/test_device.py Testing/test_jobs.py}
TAIL=18 stage demo 120 bash -c "$py -m SDFCARLib demo --out /tmp/cuda-demo --overwrite && grep -o '\"device\": \"[^\"]*\"' /tmp/cuda-demo/report.json"
# one torch thread per test process: 15 processes of 16 threads each on 16 cores did not finish in 400 s,
# with one thread each the suite took 112 s (RESULTS §39)
TAIL=25 stage suite 400 env OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $py -m pytest -q -p no:cacheprovider -p live_failures --tb=short -n "${WORKERS:-12}" --dist loadfile -rfs ${SUITE_ARGS:-}
TAIL=4 stage realistic 150 $py bench/variants.py --suite rca --case 0 \
    --protocol realistic-static-lao30-rao30 --threads "$(nproc)" '{"device": "cpu"}'
