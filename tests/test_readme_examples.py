"""Every example of the README and of the docs site marked runnable runs as written.

The pages read are README.md and every Markdown page under docs/ (not the generated
command pages, not the built site). A ``sh`` block of a page is runnable when the line
just before its fence is the HTML comment ``<!-- runnable -->`` (GitHub renders it as
nothing), with options after a
colon: ``timeout=S`` (seconds the block may take here; default 60) and
``covered-by=tests/FILE.py`` (a test of its own already runs it exactly as written, with
checks of its results: it is not run twice). An example that needs real hardware,
root, systemd, a network or a file the reader brings says so with ``<!-- manual:
REASON -->`` and is only counted; an unmarked block is counted too.

Each runnable block runs unchanged in bash (``set -eo pipefail``, so a failing line
fails it), in a fresh temporary folder as its working directory, with this checkout's
``swarm`` and ``python3`` first on PATH and in a session of its own. It must exit 0
within its timeout, print no traceback, and leave nothing running: a process of its
session still alive after bash exits is an example whose ``kill $!`` did not stop what
it started (a backgrounded ``mkdir ... && swarm ... &`` subshell, for one).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from net_helpers import live_processes

pytestmark = pytest.mark.processes  # the examples start emulators, agents and simulators

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"


def pages() -> list[Path]:
    """README.md and the docs site's own pages (generated and built ones left out)."""
    docs = ROOT / "docs"
    found = [
        p for p in sorted(docs.rglob("*.md")) if not {"_build", "commands"} & set(p.relative_to(docs).parts)
    ]
    return [README, *found]


DEFAULT_TIMEOUT = 60.0
SLACK = 4.0  # a loaded machine (2 cores shared by many jobs) gets this factor on a block's timeout
LINGER_S = 10.0  # how long a process may outlive the example's bash before it counts as left running
MARKER = re.compile(r"^<!-- (runnable|manual)(?::\s*(.*?))?\s*-->$")


@dataclass(frozen=True)
class Example:
    """One ``sh`` block: where it is, how it is marked and its text."""

    page: str  # the page's path in the checkout (README.md, docs/radios.md...)
    line: int  # 1-based line of the opening fence
    heading: str
    kind: str  # "runnable", "manual" or "unmarked"
    options: dict[str, str]
    text: str

    @property
    def name(self) -> str:
        stem = Path(self.page).stem
        return f"{stem}-L{self.line}-{re.sub(r'[^a-z0-9]+', '-', self.heading.lower()).strip('-')}"


def parse_options(raw: str) -> dict[str, str]:
    return dict(item.split("=", 1) for item in raw.split() if "=" in item)


def examples(text: str | None = None, page: str = "README.md") -> list[Example]:
    """Every ``sh`` block of every page (or of ``text``), with the marker on the line before it."""
    if text is None:
        return [e for p in pages() for e in examples(p.read_text(encoding="utf-8"), str(p.relative_to(ROOT)))]
    lines = text.splitlines()
    found: list[Example] = []
    heading, i = "", 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#") and not line.startswith("#!"):
            heading = line.lstrip("#").strip()
        if line.startswith("```"):
            end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
            if line.strip() == "```sh":
                match = MARKER.match(lines[i - 1].strip()) if i else None
                kind = match.group(1) if match else "unmarked"
                raw = (match.group(2) or "") if match else ""
                options = parse_options(raw) if kind == "runnable" else {"reason": raw}
                found.append(
                    Example(page, i + 1, heading, kind, options, "\n".join(lines[i + 1 : end]) + "\n")
                )
            i = end
        i += 1
    return found


def runnable() -> list[Example]:
    return [e for e in examples() if e.kind == "runnable" and "covered-by" not in e.options]


def session_processes(sid: int) -> list[str]:
    """The processes still alive in session ``sid`` (the block's), as "pid cmdline"."""
    alive = []
    for pid, _parent, session in live_processes():
        if session != sid:
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue  # gone meanwhile
        alive.append(f"{pid} {cmd.strip()}")
    return alive


def test_the_parser_reads_markers_and_options() -> None:
    text = "## A\n<!-- runnable: timeout=30 -->\n```sh\necho hi\n```\n"
    text += "<!-- manual: needs a radio -->\n```sh\nx\n```\n"
    text += "```python\nprint()\n```\n```sh\ny\n```\n"
    found = examples(text)
    assert [(e.kind, e.line, e.heading) for e in found] == [
        ("runnable", 3, "A"),
        ("manual", 7, "A"),
        ("unmarked", 13, "A"),
    ]
    assert found[0].options == {"timeout": "30"} and found[0].text == "echo hi\n"
    assert found[1].options == {"reason": "needs a radio"}


def test_coverage_of_the_readme_examples() -> None:
    """How many examples run here, and why the others do not (printed: ``pytest -s``)."""
    found = examples()
    by_kind = {kind: [e for e in found if e.kind == kind] for kind in ("runnable", "manual", "unmarked")}
    counts = ", ".join(f"{kind} {len(items)}" for kind, items in by_kind.items())
    print(f"\nREADME and docs sh examples: {len(found)}: {counts} (runnable: run here or by the test named)")
    for e in found:
        detail = e.options.get("reason") or e.options.get("covered-by", "")
        print(f"  {e.kind:9} {e.page:26} line {e.line:5} {e.heading[:40]:40} {detail}")
    assert len(by_kind["runnable"]) >= 6
    for e in by_kind["manual"]:
        assert e.options["reason"], f"{e.page} line {e.line}: a manual example says why it cannot run here"
    for e in by_kind["runnable"]:
        assert set(e.options) <= {"timeout", "covered-by"}, (
            f"{e.page} line {e.line}: unknown option {e.options}"
        )
        covered = e.options.get("covered-by")
        if covered:
            assert (ROOT / covered).is_file(), f"{e.page} line {e.line}: {covered} does not exist"
            assert "README" in (ROOT / covered).read_text(encoding="utf-8")


def make_targets() -> dict[str, tuple[list[str], str]]:
    """The Makefile's rules: target -> (prerequisites, recipe text)."""
    rules: dict[str, tuple[list[str], str]] = {}
    current = ""
    for line in (ROOT / "Makefile").read_text(encoding="utf-8").splitlines():
        rule = re.match(r"^([A-Za-z$()._/-]+):(?!=)\s*(.*)$", line)
        if rule and not line.startswith("\t"):
            current = rule.group(1)
            rules[current] = (rule.group(2).split(), "")
        elif line.startswith("\t") and current:
            prereqs, recipe = rules[current]
            rules[current] = (prereqs, recipe + line + "\n")
        elif not line.strip() or line.startswith("#"):
            current = ""
    return rules


def test_setup_statements_match_what_the_makefile_does() -> None:
    """README's set-up paragraph (before **Status.**) and the Makefile's messages say
    what `make setup` does: no npm, Debian's chromium packages, apt-get only as root or
    through a sudo that asks no password, page tests that fail (never skip) without a
    browser, python3's venv module."""
    readme = " ".join(README.read_text(encoding="utf-8").split("**Status.**", 1)[0].split())
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    rules = make_targets()
    reached, todo = set(), ["setup", "test", "demo"]
    while todo:
        target = todo.pop()
        if target in rules and target not in reached:
            reached.add(target)
            todo.extend(rules[target][0])
    assert "browser" in reached and "leaflet" not in reached
    assert not any("npm" in rules[t][1] for t in reached), "set-up runs npm"
    assert "No npm" in readme
    packages = re.search(r"^CHROMIUM_PKGS := (.+)$", makefile, re.M)
    assert packages is not None
    for package in packages.group(1).split():
        assert f"`{package}`" in readme, f"README's set-up does not name {package}"
    assert "asks no password" in readme and "the set-up never prompts" in readme
    for line in makefile.splitlines():  # apt-get only as root or through a sudo that never prompts
        assert "sudo " not in line or "sudo -n" in line or "echo" in line or line.startswith("#"), line
    assert "skip" not in rules["browser"][1], "the page tests fail without a browser, never skip"
    assert "the page tests then fail" in readme and "never skip" in readme
    assert 'pytest.fail("no chromium' in (ROOT / "tests" / "gcs_browser.py").read_text(encoding="utf-8")
    assert "python3-venv" in readme and "python3-venv" in makefile
    # every apt-get waits for a package lock another program holds, and says so
    apt = [line for line in makefile.splitlines() if re.search(r"SUDO apt-get", line)]  # what it runs
    assert apt and all("$(APT_WAIT)" in line for line in apt), apt
    assert "DPkg::Lock::Timeout=" in makefile and "waits up to 5 minutes for a package lock" in readme
    # the demo needs no browser: a held or failing browser install cannot stop it
    reached, todo = set(), ["demo"]
    while todo:
        target = todo.pop()
        if target in rules and target not in reached:
            reached.add(target)
            todo.extend(rules[target][0])
    assert "browser" not in reached and "the demo needs no browser" in readme


def test_agents_on_the_emulator_are_told_its_slots() -> None:
    """An agent cannot read the TDM round from its radio: an example that starts N > 2
    emulated radios gives its agents ``--slots N`` (without it they assume a pair)."""
    for e in examples():
        nodes = re.search(r"swarm radio-emu --nodes (\d+)", e.text)
        agents = [line for line in e.text.splitlines() if "swarm agent " in line]
        if nodes and int(nodes.group(1)) > 2 and agents:
            for line in agents:
                assert f"--slots {nodes.group(1)}" in line, f"{e.page} line {e.line}: {line.strip()}"


@pytest.mark.parametrize("example", runnable(), ids=lambda e: e.name)
def test_readme_example_runs_as_written(example: Example, tmp_path: Path) -> None:
    timeout = float(example.options.get("timeout", DEFAULT_TIMEOUT)) * SLACK
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env["PYTHONUNBUFFERED"] = "1"
    log_path = tmp_path.parent / f"{tmp_path.name}.log"  # not a pipe: a leftover process would hold it open
    with log_path.open("w+b") as log:
        proc = subprocess.Popen(
            ["bash", "-c", "set -eo pipefail\n" + example.text],
            cwd=tmp_path,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.seek(0)
        out = log.read().decode(errors="replace")
    if proc.returncode == -signal.SIGKILL:
        pytest.fail(f"{example.page} line {example.line} did not finish within {timeout:g} s:\n{out[-3000:]}")
    # a helper that ends by itself once its parent has gone (multiprocessing's resource
    # tracker) is not left running: give the session a few seconds to empty
    deadline = time.monotonic() + LINGER_S
    while (left := session_processes(proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.1)
    for entry in left:  # never leave them running, whatever the verdict
        try:
            os.kill(int(entry.split()[0]), signal.SIGKILL)
        except ProcessLookupError:
            pass
    assert proc.returncode == 0, (
        f"{example.page} line {example.line} exited {proc.returncode}:\n{out[-3000:]}"
    )
    assert "Traceback" not in out, f"{example.page} line {example.line} printed a traceback:\n{out[-3000:]}"
    assert not left, f"{example.page} line {example.line} left processes running: {left}\n{out[-2000:]}"
