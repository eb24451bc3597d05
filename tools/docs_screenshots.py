#!/usr/bin/env python3
"""Regenerate the operator guide's screenshots from the page tests that take them.

    .venv/bin/python tools/docs_screenshots.py          # runs the tests, copies the pictures

Each picture of ``docs/images/`` is a screenshot a browser test keeps in
``test-artifacts/`` (git-ignored) while it checks what the picture shows (the alarm
banner, the alarm list, a Go after a failsafe, the mode selector, heights after a
station restart, 20 fleet rows): this runs those tests and copies their screenshots,
so no picture in the guide is ever older than the page it shows. Exit 0 when every
test passed and every picture was copied; 1 otherwise (nothing copied from a failed
run); 130 when interrupted.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ARTIFACTS = ROOT / "test-artifacts"
IMAGES = ROOT / "docs" / "images"

#: picture -> the test that takes it
SHOTS = {
    "gcs_page_alarms.png": "tests/test_alarms_page.py",
    "gcs_page_alarm_list.png": "tests/test_alarms_page.py",
    "gcs_failsafe_go_did_not_happen.png": "tests/test_failsafe_page.py",
    "gcs_mode_selector_loiter.png": "tests/test_mode_selector.py",
    "altitude_after_station_restart.png": "tests/test_altitude_page.py",
    "gcs_fleet_20_rows.png": "tests/test_fleet_page.py",
}


def main() -> int:
    tests = sorted(set(SHOTS.values()))
    pytest = ROOT / ".venv" / "bin" / "pytest"
    cmd = [str(pytest) if pytest.exists() else sys.executable, *([] if pytest.exists() else ["-m", "pytest"])]
    try:
        run = subprocess.run([*cmd, "-q", "-p", "no:cacheprovider", *tests], cwd=ROOT)
    except KeyboardInterrupt:
        return 130
    if run.returncode != 0:
        print("docs-screenshots: a test failed: no picture copied", file=sys.stderr)
        return 1
    IMAGES.mkdir(exist_ok=True)
    missing = [name for name in SHOTS if not (ARTIFACTS / name).is_file()]
    if missing:
        print(f"docs-screenshots: no screenshot {', '.join(missing)}", file=sys.stderr)
        return 1
    for name in SHOTS:
        shutil.copyfile(ARTIFACTS / name, IMAGES / name)
    print(f"docs-screenshots: {len(SHOTS)} pictures in {IMAGES.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
