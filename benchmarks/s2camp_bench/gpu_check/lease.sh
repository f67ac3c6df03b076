#!/usr/bin/env bash
# One lease of a lent GPU machine, as one call (docs/GPU-CHECK.md, "A lease"):
#   bash benchmarks/s2camp_bench/gpu_check/lease.sh        (carrying .whl, made by python -m s2camp_bench.gpu_check.bundle)
# installs the offline bundle, runs the GPU check's stages CHECK_STAGES (the machine and the timing) within CHECK_S
# seconds of the start, then the regime command's REGIME_VARIANTS until REGIME_S, then the `cuda` tests until
# TESTS_S if a minute is left, and leaves the reports and one archive of everything measured (no scene, no
# checkpoints) in $OUT (at most 8 files come back), packed again after each command. Every command stops cleanly at
# its deadline, and `timeout` stops it 20 s later if it does not; sized for a call limit of 600 s. A second lease
# for what the first left, e.g.:
#   CHECK_STAGES="timing tests" CHECK_ARGS="--pairs splatfacto/s2camp-splat" REGIME_VARIANTS=images-alone \
#   bash benchmarks/s2camp_bench/gpu_check/lease.sh
set -u
START=$(date +%s)
CHECK_S=${CHECK_S:-230}
REGIME_S=${REGIME_S:-545}
TESTS_S=${TESTS_S:-580}
CHECK_STAGES=${CHECK_STAGES:-timing}
REGIME_VARIANTS=${REGIME_VARIANTS:-s2camp tracks-alone images-alone}
WORK=${WORK:-/tmp/lease}
OUT=${OUT:-$WORK/out}
SITE=${SITE:-/tmp/site}
PYTHON=${PYTHON:-python3}

left() { echo $((START + $1 - $(date +%s))); }

step() {  # step NAME END_S COMMAND...: COMMAND with --deadline until END_S, output in $WORK/NAME.log
    local name=$1 end=$2
    shift 2
    local seconds
    seconds=$(left "$end")
    if [ "$seconds" -lt 30 ]; then
        echo ">>> $name: not started, $seconds s left" | tee -a "$WORK/lease.log"
        return
    fi
    echo ">>> $name ($seconds s): $*" | tee -a "$WORK/lease.log"
    timeout -k 5 $((seconds + 20)) "$@" --deadline "$seconds" >"$WORK/$name.log" 2>&1
    echo "    $name: exit status $? at $(($(date +%s) - START)) s" | tee -a "$WORK/lease.log"
    pack
}

pack() {  # the reports and an archive of every record and log (no scene, no ns-train outputs) into $OUT
    local report
    for report in gpu-check/gpu-check.md regime/regime.md cuda-tests/gpu-check.md; do
        if [ -f "$WORK/$report" ]; then cp "$WORK/$report" "$OUT/${report%%/*}.md"; fi
    done
    tar -C "$WORK" -czf "$OUT/lease.tgz.part" --exclude=scene --exclude=ns-train --exclude=out . 2>/dev/null &&
        mv "$OUT/lease.tgz.part" "$OUT/lease.tgz"
}

mkdir -p "$WORK" "$OUT"
if [ -z "${NO_INSTALL:-}" ]; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl ||
        { echo "installing the bundle (.whl) failed"; exit 1; }
    export PYTHONPATH=$SITE
fi
# The installed package, not the checkout's source folder (which lacks s2camp_bench): no cwd on sys.path.
export PYTHONSAFEPATH=1 PYTHONUNBUFFERED=1
echo "installed at $(($(date +%s) - START)) s" | tee "$WORK/lease.log"

# shellcheck disable=SC2206 # CHECK_ARGS: more options of the check, as words
CHECK=("$PYTHON" -m s2camp_bench.gpu_check ${SMOKE:+--cpu-smoke} ${CHECK_ARGS:-})
# shellcheck disable=SC2086 # the stages and variants are lists of words
step gpu-check "$CHECK_S" "${CHECK[@]}" --stages $CHECK_STAGES --output-dir "$WORK/gpu-check"
# shellcheck disable=SC2086
step regime "$REGIME_S" "$PYTHON" -m s2camp_bench.gpu_check.regime ${SMOKE:+--cpu-smoke} \
    --variants $REGIME_VARIANTS --output-dir "$WORK/regime" --scene-dir "$WORK/gpu-check/scene"
case " $CHECK_STAGES " in
*" tests "*) ;;  # already run by the check
*) step cuda-tests "$TESTS_S" "${CHECK[@]}" --stages tests --output-dir "$WORK/cuda-tests" ;;
esac

pack
echo "packed at $(($(date +%s) - START)) s: $(ls "$OUT" | tr '\n' ' ')" | tee -a "$WORK/lease.log"
cat "$OUT"/*.md
