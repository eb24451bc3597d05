#!/usr/bin/env bash
# The whole test suite (what `make test` runs after the static checks), in three pytest
# sessions side by side on the machine's two cores:
#   - the process tests that run in real time and judge rates, formation errors or
#     recovery times (the `processes` marker without `light` or `waits`), one after
#     another as they always ran;
#   - the few long tests that mostly wait out a fixed stretch of real time with little
#     CPU (`waits`: a recorded 41.5 s autopilot boot, a member up for over a minute
#     before its restart), and the README's runnable examples (they share the README's
#     fixed ports, TCP 5760...), and the tests against real autopilots (`sitl`: ArduCopter
#     and PX4 SITL mostly wait for their boot), one after another;
#   - everything else: the tests that start no process, then the light process tests
#     (AT commands over ptys, a wheel build, the pre-flight check: `light`, given by
#     tests/conftest.py), one after another.
# The last runs in the foreground; the two others' logs are shown once it is done, each
# as it grows. Each session ends with its 25 slowest tests (--durations), so that a CI log
# says where the suite's time goes. Extra arguments go to every session. Exit status: the
# first session's that failed.
set -u
cd "$(dirname "$0")/.."
PYTEST=${PYTEST:-.venv/bin/pytest}
set -- --durations=25 "$@"
rt_log=$(mktemp "${TMPDIR:-/tmp}/pytest-processes.XXXXXX")
wait_log=$(mktemp "${TMPDIR:-/tmp}/pytest-waits.XXXXXX")
"$PYTEST" -p no:cacheprovider -m "processes and not light and not waits and not sitl and not slow and not hardware" "$@" >"$rt_log" 2>&1 &
rt=$!
"$PYTEST" -p no:cacheprovider -m "(waits or sitl) and not slow and not hardware" "$@" >"$wait_log" 2>&1 &
wt=$!
cleanup() { kill "$rt" "$wt" 2>/dev/null; wait "$rt" "$wt" 2>/dev/null; rm -f "$rt_log" "$wait_log"; }
trap 'cleanup; exit 130' INT TERM
"$PYTEST" -m "(not processes or light) and not waits and not sitl and not slow and not hardware" "$@"
fg=$?
echo "== the long-waiting process tests (ran beside the session above):"
tail -n +1 -f --pid="$wt" "$wait_log"
wait "$wt"
wts=$?
echo "== the real-time process tests (ran beside the sessions above):"
tail -n +1 -f --pid="$rt" "$rt_log"
wait "$rt"
rts=$?
rm -f "$rt_log" "$wait_log"
trap - INT TERM
for s in "$fg" "$wts" "$rts"; do
  if [ "$s" -ne 0 ]; then exit "$s"; fi
done
exit 0
