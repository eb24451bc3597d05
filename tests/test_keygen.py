"""``swarm keygen FILE``: 32 random bytes, mode 0600 whatever the umask, never an
overwrite, never a partly written or world-readable file; and the key it writes
signs a real swarm: two agents started from config files (the key a path relative to
the file) and a station on the emulated radios, all with the generated key, elect one
leader and the station connects both; every frame they put on the air (the
emulator's capture) carries a signature made with that key.
"""

from __future__ import annotations

import json
import os
import resource
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from radios.signing import load_key, signature
from radios.tlog import read_tlog
from swarm.cli import main as swarm_main
from swarm.cli.procs import Child, start_emulator


@pytest.fixture
def umask_000() -> Iterator[None]:
    old = os.umask(0)
    yield
    os.umask(old)


def one_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("swarm keygen: error: "), err
    return err[0]


def test_keygen_writes_32_random_bytes_mode_0600_under_umask_000(
    tmp_path: Path, umask_000: None, capsys: pytest.CaptureFixture[str]
) -> None:
    a, b = tmp_path / "a.key", tmp_path / "b.key"
    assert swarm_main(["keygen", str(a)]) == 0
    out = capsys.readouterr().out
    assert swarm_main(["keygen", str(b)]) == 0
    for path in (a, b):
        st = path.stat()
        assert stat.S_IMODE(st.st_mode) == 0o600 and st.st_size == 32
        assert load_key(path) == path.read_bytes()  # the raw form: read as is
    assert a.read_bytes() != b.read_bytes()
    assert f"wrote a new swarm signing key to {a} " in out and "mode 0600" in out
    assert "scp -p" in out and "--key FILE" in out and "sha256sum" in out


def test_keygen_refuses_to_overwrite_anything(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    existing = tmp_path / "swarm.key"
    existing.write_bytes(b"the old key")
    target = tmp_path / "target"
    dangling = tmp_path / "link.key"
    dangling.symlink_to(target)
    for path in (existing, dangling, tmp_path):
        assert swarm_main(["keygen", str(path)]) == 2
        assert "exists: a key is never overwritten" in one_error(capsys)
    assert existing.read_bytes() == b"the old key" and not target.exists()


def test_keygen_wants_an_existing_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "no-such-folder" / "swarm.key"
    assert swarm_main(["keygen", str(path)]) == 2
    assert f"the folder {path.parent} does not exist (create it first)" in one_error(capsys)
    assert not path.parent.exists()


@pytest.mark.processes
def test_a_failed_write_leaves_no_file(tmp_path: Path) -> None:
    """A write that fails half way (a file-size limit of 16 bytes: the first 16 bytes
    go, then EFBIG) exits 1 with one line and removes what it created."""
    path = tmp_path / "swarm.key"

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (16, 16))

    p = subprocess.run(
        [sys.executable, "-m", "swarm.cli", "keygen", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        preexec_fn=limit,
    )
    assert p.returncode == 1, p.stderr
    err = p.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("swarm keygen: error: ") and "no key written" in err[0]
    assert not path.exists() and list(tmp_path.iterdir()) == []


# -- the generated key signs a real swarm ---------------------------------------------


def _last_state(child: Child) -> dict[str, Any] | None:
    for line in reversed(list(child.lines)):
        obj = json.loads(line)
        if obj.get("event") == "state":
            return dict(obj)
    return None


def _leader(agents: list[Child]) -> int | None:
    states = [_last_state(c) for c in agents]
    if any(s is None or s["phase"] not in ("LEADER", "MEMBER") for s in states):
        return None
    leaders = {s["leader"] for s in states if s is not None}
    return leaders.pop() if len(leaders) == 1 else None


def _connected(url: str) -> set[int]:
    import urllib.request

    with urllib.request.urlopen(url + "api/state", timeout=10) as r:
        return {a["id"] for a in json.loads(r.read())["agents"] if a["connected"]}


@pytest.mark.processes
def test_agents_from_config_files_and_a_station_sign_with_the_generated_key(tmp_path: Path) -> None:
    conf = tmp_path / "etc"
    conf.mkdir()
    assert swarm_main(["keygen", str(conf / "swarm.key")]) == 0
    air = tmp_path / "air.tlog"
    emu, radios = start_emulator(3, tmp_path, "--capture", str(air))
    children: list[Child] = []
    try:
        for k in (1, 2):
            path = conf / f"agent{k}.toml"
            path.write_text(
                f'name = "agent{k}"\nid = {k}\nradio = "{radios[k - 1]}"\nkey = "swarm.key"\n'
                'profile = "fast"\nslots = 3\njson = true\n'
            )
            children.append(Child(["agent", "--config", str(path)], name=f"agent{k}"))
        http = f"127.0.0.1:{free_port()}"
        gcs = Child(
            ["gcs", "--radio", radios[2], "--key", str(conf / "swarm.key"), "--json", "--http", http],
            name="gcs",
        )
        children.append(gcs)
        ready = json.loads(gcs.wait_lines(1, 60)[0])
        for c in children[:2]:
            assert json.loads(c.wait_lines(1, 60)[0])["event"] == "ready"
        leader = wait_until(
            lambda: _leader(children[:2]), "one leader of two signed agents", 90, 0.2, children=children
        )
        assert leader in (1, 2)
        wait_until(
            lambda: _connected(ready["url"]) == {1, 2},
            "the station to connect both",
            90,
            0.5,
            children=children,
        )
    finally:
        for c in children:
            c.stop(grace=5)
        emu.stop()
    key = load_key(conf / "swarm.key")
    senders: dict[int, int] = {}
    with read_tlog(air) as frames:
        for rec in frames:
            f = rec.frame
            if f.sysid in (1, 2, 255):  # the nodes' frames, not the radios' own reports
                assert f.signed and signature(key, f.raw[:-6]) == f.raw[-6:], f.name
                senders[f.sysid] = senders.get(f.sysid, 0) + 1
    assert set(senders) == {1, 2, 255}
