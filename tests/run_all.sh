#!/usr/bin/env bash
# The whole test suite (what `make test` runs after the static checks and the docs), in
# two pytest sessions:
#   1. every test that judges no time, in parallel pytest-xdist workers (WORKERS, default
#      4 for every 2 cores: most process tests wait on real time with little CPU). The
#      tests of a module that starts processes stay on one worker in their order, and the
#      tests of the real autopilots and of the fixed ports each run one after another
#      (tests/conftest.py gives the groups). A test that hangs fails at its timeout; a
#      worker that dies fails the test it ran and is replaced: the session goes on.
#   2. the tests that judge time (marker `timing`: a rate, a duration, CPU, an error
#      measured in real time), one after another, alone: by default after the first
#      (TIMING=beside runs them beside it, quicker on a quiet machine).
# Each session ends with its 25 slowest tests (--durations), so that a CI log says where
# the suite's time goes. Extra arguments go to both sessions. Exit status: the first
# session's that failed.
set -u
cd "$(dirname "$0")/.."
PYTEST=${PYTEST:-.venv/bin/pytest}
cores=$(nproc 2>/dev/null || echo 2)
WORKERS=${WORKERS:-$((cores * 2))}
set -- --durations=25 "$@"
select="not slow and not hardware"
timing_log=$(mktemp "${TMPDIR:-/tmp}/pytest-timing.XXXXXX")
tm=""
cleanup() {
  if [ -n "$tm" ]; then kill "$tm" 2>/dev/null; wait "$tm" 2>/dev/null; fi
  rm -f "$timing_log"
}
trap 'cleanup; exit 130' INT TERM
if [ "${TIMING:-after}" = beside ]; then
  "$PYTEST" -p no:cacheprovider -m "timing and $select" "$@" >"$timing_log" 2>&1 &
  tm=$!
fi
echo "== the tests that judge no time, in $WORKERS parallel workers:"
"$PYTEST" -p no:cacheprovider -n "$WORKERS" --dist loadgroup -m "not timing and $select" "$@"
par=$?
if [ -n "$tm" ]; then
  echo "== the tests that judge time, one after another (ran beside the session above):"
  tail -n +1 -f --pid="$tm" "$timing_log"
  wait "$tm"
  tms=$?
else
  echo "== the tests that judge time, one after another, alone:"
  "$PYTEST" -p no:cacheprovider -m "timing and $select" "$@"
  tms=$?
fi
rm -f "$timing_log"
trap - INT TERM
for s in "$par" "$tms"; do
  if [ "$s" -ne 0 ]; then exit "$s"; fi
done
exit 0
