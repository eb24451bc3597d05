"""What users install: the wheel and the sdist carry the station's page and the pinned
Leaflet, ``swarm --version`` names the release, and every runtime dependency has a
wheel for a 64-bit Raspberry Pi.

Theory of operation
-------------------
* The vendored Leaflet (``swarm/runtime/station/vendor/leaflet``, copied from the npm package
  by ``make leaflet``) is checked against its ``SHA256SUMS``, and its version against
  the pin in ``package.json`` and ``package-lock.json``: a file changed by hand, a
  file missing or a version drifting fails here.
* The package test builds the sdist and then the wheel *from that sdist* (``python -m
  build``, as a user's pip would, with no npm anywhere), installs the wheel into a
  fresh virtual environment in a temporary folder outside the checkout, and runs
  ``swarm --version`` and ``swarm gcs`` from there (cwd outside the checkout, no
  ``PYTHONPATH``): the page, its scripts and Leaflet must answer 200 with the bytes of
  the checkout. The dependencies come from a wheel folder built once from the pinned
  set with pip (in the test environment, ``.venv/wheelhouse``, per set of pins), so
  a warm run needs no network.
* The Raspberry Pi check asks pip to resolve the pinned runtime set and all that it
  pulls in for CPython 3.11 on aarch64 with glibc 2.36 (Raspberry Pi OS bookworm,
  64-bit) with wheels only: metadata only by default (seconds, needs PyPI), every
  file downloaded under ``-m slow``. crcmod publishes no wheel at all: it is checked
  on its own (an sdist that installs as pure Python where no C compiler is found).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tarfile
import tomllib
import urllib.error
import urllib.request
import venv
import zipfile
from pathlib import Path

import pytest
from net_helpers import free_port, wait_until

from swarm.cli import main as swarm_main

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ROOT / "swarm" / "runtime" / "station"
LEAFLET = RUNTIME / "vendor" / "leaflet"
#: what the page needs, under swarm/runtime/station; served as /, /static/..., /vendor/leaflet/...
#: every file of the page's folder ships (a new script must not be left out of the wheel)
PAGE_FILES = tuple(sorted(f"static/{p.name}" for p in (RUNTIME / "static").iterdir() if p.is_file()))
assert {"static/index.html", "static/app.js", "static/app.css"} <= set(PAGE_FILES)
LEAFLET_FILES = (
    "vendor/leaflet/leaflet.js",
    "vendor/leaflet/leaflet.css",
    "vendor/leaflet/LICENSE",
    "vendor/leaflet/SHA256SUMS",
    "vendor/leaflet/images/marker-icon.png",
    "vendor/leaflet/images/marker-icon-2x.png",
    "vendor/leaflet/images/marker-shadow.png",
    "vendor/leaflet/images/layers.png",
    "vendor/leaflet/images/layers-2x.png",
)
URLS = {
    "/": "static/index.html",
    "/static/app.js": "static/app.js",
    "/static/app.css": "static/app.css",
    "/static/icon.svg": "static/icon.svg",
    "/static/alerts.js": "static/alerts.js",
    "/vendor/leaflet/leaflet.js": "vendor/leaflet/leaflet.js",
    "/vendor/leaflet/leaflet.css": "vendor/leaflet/leaflet.css",
    "/vendor/leaflet/images/marker-icon.png": "vendor/leaflet/images/marker-icon.png",
}
DEADLINE = 60.0
#: Raspberry Pi OS bookworm (64-bit): CPython 3.11, glibc 2.36, aarch64
PI_PYTHON = "3.11"
PI_GLIBC_MINOR = 36
#: pinned runtime packages that publish no wheel at all (sdist only), and why that is fine
SDIST_ONLY = {"crcmod": "builds its C extension where gcc and python3-dev are installed, else pure Python"}


def _project() -> dict:
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return dict(tomllib.load(fh)["project"])


def _pinned() -> list[str]:
    return list(_project()["dependencies"])


# -- swarm --version ---------------------------------------------------------------------
def test_version_names_the_installed_release(capsys: pytest.CaptureFixture[str]) -> None:
    assert swarm_main(["--version"]) == 0
    out = capsys.readouterr().out
    assert out == f"swarm (uav-swarm) {_project()['version']}\n"
    # before the command, like the other global options; after it, it is the command's
    assert swarm_main(["--version", "gcs"]) == 0
    assert capsys.readouterr().out == out


def test_version_without_installed_metadata_says_so(tmp_path: Path) -> None:
    """The packages' sources on sys.path with no metadata anywhere (a copy, without
    the checkout's egg-info; no site-packages): the version is unknown, said so, exit 0."""
    for pkg in ("swarm", "radios", "firmware_bridge"):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); import swarm.cli as c; sys.exit(c.main(sys.argv[2:]))"
    )
    argv = [sys.executable, "-I", "-S", "-c", code, str(tmp_path), "--version"]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "swarm (uav-swarm) unknown (not installed: pip install . or make setup)\n"


# -- the vendored Leaflet ------------------------------------------------------------------
def test_vendored_leaflet_is_the_pinned_release_with_its_licence() -> None:
    pin = json.loads((ROOT / "package.json").read_text())["dependencies"]["leaflet"]
    lock = json.loads((ROOT / "package-lock.json").read_text())["packages"]["node_modules/leaflet"]
    assert pin == lock["version"] == "1.9.4"
    head = (LEAFLET / "leaflet.js").read_text(encoding="utf-8")[:200]
    assert f"Leaflet {pin}," in head
    assert (LEAFLET / "LICENSE").read_text().startswith("BSD 2-Clause License")
    sums = {}
    for line in (LEAFLET / "SHA256SUMS").read_text().splitlines():
        digest, name = line.split(maxsplit=1)
        sums[name] = digest
    present = {
        p.relative_to(LEAFLET).as_posix()
        for p in LEAFLET.rglob("*")
        if p.is_file() and p.name != "SHA256SUMS"
    }
    assert present == set(sums), "files in the vendored Leaflet and its SHA256SUMS differ"
    for name, digest in sums.items():
        assert hashlib.sha256((LEAFLET / name).read_bytes()).hexdigest() == digest, name
    assert {f"vendor/leaflet/{n}" for n in sums} | {"vendor/leaflet/SHA256SUMS"} == set(LEAFLET_FILES)


# -- the wheel and the sdist, installed outside the checkout -------------------------------
def _run(*argv: str | Path, timeout: float = 600, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=timeout, **kw)  # type: ignore[call-overload]


def _pip(*args: str | Path, timeout: float = 600, **kw: object) -> subprocess.CompletedProcess[str]:
    """The pip of the interpreter running the tests."""
    return _run(sys.executable, "-m", "pip", *args, timeout=timeout, **kw)


def _build(out: Path) -> tuple[Path, Path]:
    """The sdist, then the wheel built from it (no npm, no network)."""
    r = _run(sys.executable, "-m", "build", "--no-isolation", "--outdir", out, ROOT, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    (sdist,) = out.glob("uav_swarm-*.tar.gz")
    (wheel,) = out.glob("uav_swarm-*.whl")
    return sdist, wheel


def _wheelhouse() -> Path:
    """Wheels of the pinned runtime set (and what it pulls in), built once with pip
    from the index (or its cache) into the test environment, kept until the pins change."""
    key = hashlib.sha256("\n".join(sorted(_pinned())).encode()).hexdigest()[:16]
    house = Path(sys.prefix) / "wheelhouse" / key
    done = house / ".complete"
    if not done.is_file():
        r = _pip("wheel", "--quiet", "--wheel-dir", house, *_pinned())
        assert r.returncode == 0, "pip wheel of the pinned set failed (network?): " + r.stderr[-2000:]
        done.touch()
    return house


def _fresh_venv(where: Path, wheel: Path) -> Path:
    """A new virtual environment with the wheel and its dependencies; its bin/."""
    venv.EnvBuilder(with_pip=False).create(where)
    house = _wheelhouse()
    r = _pip(
        *("--python", where / "bin" / "python", "install", "--quiet", "--no-compile"),
        *("--no-index", "--find-links", house, wheel),
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return where / "bin"


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


@pytest.mark.processes
def test_installed_wheel_serves_the_page_and_leaflet_outside_the_checkout(tmp_path: Path) -> None:
    sdist, wheel = _build(tmp_path / "dist")
    with tarfile.open(sdist) as tf:
        in_sdist = {n.partition("/")[2] for n in tf.getnames()}
    with zipfile.ZipFile(wheel) as zf:
        in_wheel = set(zf.namelist())
    for rel in PAGE_FILES + LEAFLET_FILES:
        assert f"swarm/runtime/station/{rel}" in in_sdist, f"the sdist lacks {rel}"
        assert f"swarm/runtime/station/{rel}" in in_wheel, f"the wheel lacks {rel}"
    assert not any("node_modules" in n for n in in_sdist | in_wheel)
    # the wheel carries the product, not the project's harness: no tools/, and no module
    # that reads the checkout's tests folder (recorded traces, the demo capture)
    assert not any(n.startswith("tools/") for n in in_wheel)
    with zipfile.ZipFile(wheel) as zf:
        reads_tests = [n for n in zf.namelist() if n.endswith(".py") and b'/ "tests"' in zf.read(n)]
    assert reads_tests == [], reads_tests

    bin_ = _fresh_venv(tmp_path / "venv", wheel)
    away = tmp_path / "elsewhere"
    away.mkdir()
    r = _run(bin_ / "swarm", "--version", cwd=away, env=_clean_env(), timeout=60)
    assert r.returncode == 0 and r.stdout == f"swarm (uav-swarm) {_project()['version']}\n", r
    r = _run(bin_ / "python", "-c", "import swarm; print(swarm.__file__)", cwd=away, env=_clean_env())
    assert Path(r.stdout.strip()).is_relative_to(tmp_path / "venv"), r

    out, err = tmp_path / "gcs.out", tmp_path / "gcs.err"
    argv = [str(bin_ / "swarm"), "gcs", "--http", f"127.0.0.1:{free_port()}", "--tiles", "none", "--json"]
    argv += ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"]
    with open(out, "w") as fo, open(err, "w") as fe:
        gcs = subprocess.Popen(argv, cwd=away, env=_clean_env(), stdout=fo, stderr=fe, start_new_session=True)
    try:

        def ready() -> dict | None:
            assert gcs.poll() is None, f"swarm gcs exited {gcs.returncode}: {err.read_text()[-2000:]}"
            lines = out.read_text().splitlines()
            return json.loads(lines[0]) if lines else None

        line = wait_until(ready, "swarm gcs's ready line", DEADLINE)
        assert line["event"] == "ready", line
        for path, rel in URLS.items():
            status, body = _get(line["url"].rstrip("/") + path)
            assert status == 200, f"{path}: {status} {body[:200]!r}"
            assert body == (RUNTIME / rel).read_bytes(), f"{path}: not the checkout's {rel}"
        status, _ = _get(line["url"] + "vendor/leaflet/nope.js")
        assert status == 404
        gcs.send_signal(signal.SIGTERM)
        assert gcs.wait(30) == 0, err.read_text()[-2000:]
    finally:
        if gcs.poll() is None:
            os.killpg(gcs.pid, signal.SIGKILL)
            gcs.wait(10)


# -- Raspberry Pi (64-bit Raspberry Pi OS bookworm) wheels ---------------------------------
def _pi_platforms() -> list[str]:
    """pip's --platform list for glibc 2.36 on aarch64 (pip takes exact tags only)."""
    tags = ["manylinux2014_aarch64"] + [f"manylinux_2_{m}_aarch64" for m in range(17, PI_GLIBC_MINOR + 1)]
    return [a for t in tags for a in ("--platform", t)]


def _pi_args() -> list[str]:
    return [*_pi_platforms(), "--python-version", PI_PYTHON, "--implementation", "cp", "--abi", "cp311"]


WHEEL_FOR_PI = re.compile(
    r"-(cp311-cp311|cp3\d+-abi3|py3-none|py2\.py3-none)-(manylinux\S*aarch64|any)\.whl$"
)


def _name(req: str) -> str:
    return re.split(r"[=<>!~ \[;]", req, maxsplit=1)[0].lower()


def _requirements() -> tuple[list[str], list[str]]:
    """The pinned runtime set split into (wheels expected, sdist only)."""
    wheels: list[str] = []
    sdists: list[str] = []
    for req in _pinned():
        (sdists if _name(req) in SDIST_ONLY else wheels).append(req)
    assert len(sdists) == len(SDIST_ONLY), "SDIST_ONLY names a package that is no longer pinned"
    return wheels, sdists


def _pip_report(tmp: Path, reqs: list[str], *extra: str) -> list[tuple[str, str]]:
    """(name, file name) of what pip would install on the Pi (metadata only)."""
    tmp.mkdir(parents=True, exist_ok=True)
    report = tmp / "report.json"
    args: list[str | Path] = ["install", "--quiet", "--dry-run", "--ignore-installed", "--target", tmp / "t"]
    r = _pip(*args, "--report", report, *_pi_args(), *extra, *reqs, timeout=300)
    assert r.returncode == 0, "no Pi install for " + " ".join(reqs) + ": " + r.stderr[-3000:]
    got = json.loads(report.read_text())["install"]
    return [(i["metadata"]["name"].lower(), i["download_info"]["url"].rsplit("/", 1)[-1]) for i in got]


@pytest.mark.processes
def test_every_pinned_dependency_has_a_wheel_for_the_pi(tmp_path: Path) -> None:
    wheels, sdists = _requirements()
    got = _pip_report(tmp_path, wheels, "--only-binary=:all:")
    names = {n for n, _ in got}
    for req in wheels:
        assert _name(req) in names, req
    bad = [f for _, f in got if not WHEEL_FOR_PI.search(f)]
    assert not bad, f"not wheels for aarch64 CPython 3.11: {bad}"
    for req in sdists:  # one source archive, no dependencies
        ((_, file),) = _pip_report(tmp_path / _name(req), [req], "--no-deps")
        assert file.endswith(".tar.gz"), f"{file}: a wheel now, drop {_name(req)} from SDIST_ONLY"


@pytest.mark.slow
@pytest.mark.processes
def test_pi_wheels_download(tmp_path: Path) -> None:
    """Every file, downloaded: what a Pi installs with ``pip install --no-index
    --find-links DIR``. The sdist-only packages build where no C compiler is found
    (pure Python), as on a Pi without gcc or python3-dev."""
    wheels, sdists = _requirements()
    house = tmp_path / "pi"
    for reqs, extra in ((wheels, "--only-binary=:all:"), (sdists, "--no-deps")):
        r = _pip("download", "--quiet", "-d", house, *_pi_args(), extra, *reqs, timeout=1200)
        assert r.returncode == 0, r.stderr[-3000:]
    files = sorted(p.name for p in house.iterdir())
    assert all(WHEEL_FOR_PI.search(f) or f.endswith(".tar.gz") for f in files), files
    for sdist in house.glob("*.tar.gz"):
        env = {**os.environ, "CC": "/bin/false"}  # no working C compiler
        r = _pip("wheel", "--quiet", "--no-deps", "--no-cache-dir", "-w", tmp_path / "built", sdist, env=env)
        assert r.returncode == 0, r.stderr[-3000:]
    built = sorted(p.name for p in (tmp_path / "built").iterdir())
    assert len(built) == len(SDIST_ONLY) and all(b.endswith("-py3-none-any.whl") for b in built), built
