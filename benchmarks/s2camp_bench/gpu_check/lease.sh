#!/usr/bin/env bash
# One lease of a lent GPU machine, as one call (docs/GPU-CHECK.md, "A lease"), carrying .whl (make gpu-bundle):
#   bash benchmarks/s2camp_bench/gpu_check/lease.sh
# installs the offline bundle (this repository's two packages among it) and runs the installed GPU check: its
# stages CHECK_STAGES (CHECK_ARGS: more options) until CHECK_S seconds after the start, then the `cuda` tests until
# TESTS_S unless the check ran them. After each the report and one archive of everything measured (no scene, no
# checkpoints) are packed into $OUT. The check stops cleanly at its deadline; `timeout` stops it 20 s later if it
# does not, and its report is then rebuilt from its records. A second lease for what the first left, e.g.:
#   CHECK_STAGES="timing regime tests" CHECK_ARGS="--groups splat-off/s2camp-splat-so3xr3/s2camp-splat
#   --regime-variants images-alone" bash benchmarks/s2camp_bench/gpu_check/lease.sh
set -u
START=$(date +%s)
CHECK_S=${CHECK_S:-560}
TESTS_S=${TESTS_S:-590}
CHECK_STAGES=${CHECK_STAGES:-timing regime}
CHECK_ARGS=${CHECK_ARGS:---groups off/s2camp-so3xr3/s2camp}
WORK=${WORK:-/tmp/lease}
OUT=${OUT:-$WORK/out}
SITE=${SITE:-/tmp/site}
PYTHON=${PYTHON:-python3}

step() {  # step NAME END_S ARGS...: the check with ARGS and --deadline until END_S, its output in $WORK/NAME.log
    local name=$1 end=$2 seconds status
    shift 2
    seconds=$((START + end - $(date +%s)))
    if [ "$seconds" -lt 30 ]; then
        echo ">>> $name: not started, $seconds s left" | tee -a "$WORK/lease.log"
        return
    fi
    echo ">>> $name ($seconds s): $*" | tee -a "$WORK/lease.log"
    timeout -k 5 $((seconds + 20)) "${CHECK[@]}" "$@" --deadline "$seconds" --output-dir "$WORK/$name" \
        >"$WORK/$name.log" 2>&1
    status=$?
    echo "    $name: exit status $status at $(($(date +%s) - START)) s" | tee -a "$WORK/lease.log"
    if [ "$status" -ge 124 ]; then  # stopped by timeout: the report from what it recorded
        "${CHECK[@]}" "$@" --report-from "$WORK/$name" --output-dir "$WORK/$name" >>"$WORK/$name.log" 2>&1
    fi
    cp "$WORK/$name/gpu-check.md" "$OUT/$name.md" 2>/dev/null
    tar -C "$WORK" -czf "$OUT/lease.tgz.part" --exclude=scene --exclude=ns-train --exclude=out . 2>/dev/null &&
        mv "$OUT/lease.tgz.part" "$OUT/lease.tgz"
}

mkdir -p "$WORK" "$OUT"
if [ -z "${NO_INSTALL:-}" ]; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl ||
        { echo "installing the bundle (.whl) failed"; exit 1; }
    export PYTHONPATH=$SITE
fi
# The installed packages, not the checkout's source folders: no working folder on sys.path.
export PYTHONSAFEPATH=1 PYTHONUNBUFFERED=1
echo "installed at $(($(date +%s) - START)) s" | tee "$WORK/lease.log"

# shellcheck disable=SC2206 # CHECK_ARGS, CHECK_STAGES: lists of words
CHECK=("$PYTHON" -m s2camp_bench.gpu_check ${SMOKE:+--cpu-smoke} ${CHECK_ARGS})
# shellcheck disable=SC2086
step gpu-check "$CHECK_S" --stages $CHECK_STAGES
case " $CHECK_STAGES " in
*" tests "*) ;;  # already run by the check
*) step cuda-tests "$TESTS_S" --stages tests ;;
esac
echo "packed at $(($(date +%s) - START)) s: $(ls "$OUT" | tr '\n' ' ')" | tee -a "$WORK/lease.log"
cat "$OUT"/*.md
