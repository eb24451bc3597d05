#!/usr/bin/env bash
# The whole test suite (what `make test` runs after the static checks), in two pytest
# sessions side by side on the machine's two cores:
#   - the process tests that run in real time and judge rates, formation errors or
#     recovery times (the `processes` marker without `light`), one after another as
#     they always ran: their log is shown as it grows once the other session is done;
#   - everything else: the tests that start no process, then the light process tests
#     (AT commands over ptys, a wheel build, the pre-flight check: `light`, given by
#     tests/conftest.py), one after another.
# Extra arguments go to both sessions. Exit status: the first session's that failed.
set -u
cd "$(dirname "$0")/.."
PYTEST=${PYTEST:-.venv/bin/pytest}
log=$(mktemp "${TMPDIR:-/tmp}/pytest-processes.XXXXXX")
"$PYTEST" -p no:cacheprovider -m "processes and not light and not slow and not hardware" "$@" >"$log" 2>&1 &
bg=$!
trap 'kill "$bg" 2>/dev/null; wait "$bg" 2>/dev/null; rm -f "$log"; exit 130' INT TERM
"$PYTEST" -m "(not processes or light) and not slow and not hardware" "$@"
fg=$?
echo "== the real-time process tests (running beside the session above):"
tail -n +1 -f --pid="$bg" "$log"
wait "$bg"
bgs=$?
rm -f "$log"
trap - INT TERM
if [ "$fg" -ne 0 ]; then exit "$fg"; fi
exit "$bgs"
