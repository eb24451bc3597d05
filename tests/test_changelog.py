"""CHANGELOG.md is release notes: versions with dates, grouped by Added, Changed, Fixed
and Security, the newest the package's own version; the next release is written from
fragments in changes/ by towncrier (run here, on a copy, as a release would)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
GROUPS = {"Added", "Changed", "Fixed", "Security"}


def test_releases_have_dates_and_only_the_four_groups() -> None:
    text = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    releases = re.findall(r"^## (\d+\.\d+\.\d+) \((\d{4}-\d{2}-\d{2})\)$", text, re.M)
    headings = re.findall(r"^## .*$", text, re.M)
    assert len(releases) == len(headings) >= 2, headings  # no "Unreleased", no journal entry
    version = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    assert releases[0][0] == version
    assert [r[1] for r in releases] == sorted((r[1] for r in releases), reverse=True)
    assert set(re.findall(r"^### (.*)$", text, re.M)) <= GROUPS


def test_a_fragment_becomes_the_next_release(tmp_path: Path) -> None:
    for name in ("pyproject.toml", "CHANGELOG.md"):
        shutil.copy(ROOT / name, tmp_path / name)
    shutil.copytree(ROOT / "changes", tmp_path / "changes")
    (tmp_path / "changes" / "28.fixed.md").write_text("A station on a busy port exits 2.\n")
    towncrier = Path(sys.executable).parent / "towncrier"
    run = subprocess.run(
        [str(towncrier), "build", "--version", "9.9.9", "--date", "2099-01-01", "--yes"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    text = (tmp_path / "CHANGELOG.md").read_text(encoding="utf-8")
    new = text.index("## 9.9.9 (2099-01-01)")
    assert new < text.index("## 0.2.0 (") and text.index("### Fixed", new) < text.index("## 0.2.0 (")
    assert "- A station on a busy port exits 2. (issue 28)" in text
    assert not (tmp_path / "changes" / "28.fixed.md").exists()  # gathered, then removed
    assert (tmp_path / "changes" / "README.md").exists()  # the folder's own note stays
