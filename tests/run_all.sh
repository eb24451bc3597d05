#!/usr/bin/env bash
# The whole test suite (what `make test` runs after the static checks and the docs), in
# three pytest sessions:
#   1. every test that judges no time, in parallel pytest-xdist workers (WORKERS, default
#      twice the cores: most process tests wait on real time with little CPU). The tests
#      of a module that starts processes stay on one worker in their order, and the tests
#      of the fixed ports run one after another (tests/conftest.py gives the groups). A
#      test that hangs fails at its timeout; a worker that dies fails the test it ran and
#      is replaced: the session goes on.
#   2. then, side by side, two sessions that run their tests one after another: the tests
#      that judge time (marker `timing`: a rate, a duration, CPU, an error measured in
#      real time), and the tests against the real autopilots (marker `sitl`: PX4 leaves
#      offboard control when its setpoint stream pauses half a second, as it would on a
#      starved companion computer, so they never run beside the parallel workers).
# Each session ends with its 25 slowest tests (--durations), so that a CI log says where
# the suite's time goes. Extra arguments go to every session. Exit status: the first
# session's that failed.
set -u
cd "$(dirname "$0")/.."
PYTEST=${PYTEST:-.venv/bin/pytest}
cores=$(nproc 2>/dev/null || echo 2)
WORKERS=${WORKERS:-$((cores * 2))}
set -- --durations=25 "$@"
select="not slow and not hardware"
sitl_log=$(mktemp "${TMPDIR:-/tmp}/pytest-sitl.XXXXXX")
st=""
cleanup() {
  if [ -n "$st" ]; then kill "$st" 2>/dev/null; wait "$st" 2>/dev/null; fi
  rm -f "$sitl_log"
}
trap 'cleanup; exit 130' INT TERM
echo "== the tests that judge no time, in $WORKERS parallel workers:"
"$PYTEST" -p no:cacheprovider -n "$WORKERS" --dist loadgroup -m "not timing and not sitl and $select" "$@"
par=$?
"$PYTEST" -p no:cacheprovider -m "sitl and not timing and $select" "$@" >"$sitl_log" 2>&1 &
st=$!
echo "== the tests that judge time, one after another:"
"$PYTEST" -p no:cacheprovider -m "timing and $select" "$@"
tms=$?
echo "== the tests against real autopilots, one after another (ran beside the session above):"
tail -n +1 -f --pid="$st" "$sitl_log"
wait "$st"
sts=$?
st=""
if [ "$sts" -eq 5 ]; then sts=0; fi  # no real autopilots here: none selected (the session says so)
rm -f "$sitl_log"
trap - INT TERM
for s in "$par" "$tms" "$sts"; do
  if [ "$s" -ne 0 ]; then exit "$s"; fi
done
exit 0
