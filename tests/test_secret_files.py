"""Secrets handled like secrets: a token file, a swarm key file or a config file
holding the token that others on the machine may read (or change) stops the command
at start, exit 2, with one line naming the file, its mode and the fix; the shipped
service set-up (settings and token 0640 root:<the service's group>, key 0400 the
service user's) starts.

The commands run as real processes (a refused one must exit, not serve); the rules
themselves (:func:`radios.secretfile.secret_file_problem`) are checked on real files
without processes.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from net_helpers import free_port

from radios.secretfile import KEY, TOKEN, config_file_problem, secret_file_problem
from swarm.cli.procs import Child, ChildError

TOKEN_TEXT = "secret-files-test-token-0123456789"


def _file(tmp_path: Path, name: str, text: str, mode: int, gid: int | None = None) -> Path:
    path = tmp_path / name
    path.write_text(text)
    path.chmod(mode)
    if gid is not None:
        os.chown(path, -1, gid)
    return path


def _other_gid() -> int:
    """A group this process is not in (its effective group is not it)."""
    return next(g for g in (65534, 1, 2, 3) if g != os.getegid())


def _run(argv: list[str], timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """``swarm ARGV``: a refused command's exit; one that starts is stopped after its first
    line (its ready line) and reported with returncode None."""
    child = Child(argv, name=argv[0])
    try:
        child.wait_lines(1, timeout)
    except ChildError:
        pass  # it exited
    code = child.proc.poll()
    child.stop()
    return subprocess.CompletedProcess(argv, code, "\n".join(child.lines), "\n".join(child.errors))  # type: ignore[arg-type]


def _zenoh() -> list[str]:
    return ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"]


def _gcs(*extra: str) -> list[str]:
    return ["gcs", *_zenoh(), "--http", "127.0.0.1:0", "--tiles", "none", *extra]


def _agent(*extra: str) -> list[str]:
    return ["agent", "--name", "a1", "--id", "1", *_zenoh(), *extra]


def _refused(done: subprocess.CompletedProcess[str], prog: str, path: Path, mode: str, who: str) -> None:
    assert done.returncode == 2, (done.returncode, done.stdout[-500:], done.stderr[-2000:])
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    line = lines[0]
    assert line.startswith(f"swarm {prog}: error: ") and str(path) in line, line
    assert f"mode {mode}" in line and who in line and line.endswith(f"fix: chmod 600 {path}"), line


@pytest.mark.processes
@pytest.mark.parametrize(
    ("what", "mode", "who"),
    [
        ("token_file", 0o644, "readable by others"),
        ("config_with_token", 0o666, "readable and writable by others"),
        ("agent_key", 0o644, "readable by its group and others"),
        ("gcs_key", 0o640, "readable by its group"),
    ],
)
def test_a_secret_others_can_read_stops_the_command(tmp_path: Path, what: str, mode: int, who: str) -> None:
    if what == "token_file":
        path = _file(tmp_path, "gcs.token", TOKEN_TEXT + "\n", mode)
        prog, argv = "gcs", _gcs("--token-file", str(path))
    elif what == "config_with_token":
        path = _file(tmp_path, "gcs.toml", f'token = "{TOKEN_TEXT}"\n', mode)
        prog, argv = "gcs", _gcs("--config", str(path))
    elif what == "agent_key":
        path = _file(tmp_path, "swarm.key", "a passphrase for the swarm\n", mode)
        prog, argv = "agent", _agent("--key", str(path))
    else:
        path = _file(tmp_path, "swarm.key", "a passphrase for the swarm\n", mode)
        prog, argv = "gcs", _gcs("--key", str(path))
    _refused(_run(argv), prog, path, f"{mode:04o}", who)


@pytest.mark.processes
def test_the_shipped_service_set_up_starts(tmp_path: Path) -> None:
    """As the units install it: settings and token 0640 root:<the service's group> (here
    this process's own group), the key 0400."""
    gid = os.getegid()
    token = _file(tmp_path, "gcs.token", TOKEN_TEXT + "\n", 0o640, gid)
    key = _file(tmp_path, "swarm.key", "a passphrase for the swarm\n", 0o400)
    conf = _file(
        tmp_path,
        "gcs.toml",
        f'token = "{TOKEN_TEXT}"\nkey = "swarm.key"\nhttp = "127.0.0.1:0"\ntiles = "none"\n'
        f'zenoh_listen = ["tcp/127.0.0.1:{free_port()}"]\n',
        0o640,
        gid,
    )
    for argv in (["gcs", "--config", str(conf)], _gcs("--token-file", str(token), "--key", str(key))):
        done = _run(argv)
        assert done.returncode is None and " ready" in done.stdout, (argv, done.stdout, done.stderr)
    done = _run(_agent("--key", str(key)))
    assert done.returncode is None and " ready" in done.stdout, (done.stdout, done.stderr)


def test_the_rules_on_real_files(tmp_path: Path) -> None:
    other = _other_gid()
    own = os.getegid()
    cases = [
        # (policy, mode, group, problem or None)
        (KEY, 0o600, own, None),
        (KEY, 0o400, own, None),
        (KEY, 0o640, own, "mode 0640: readable by its group"),
        (KEY, 0o604, own, "mode 0604: readable by others"),
        (KEY, 0o620, own, "mode 0620: writable by its group"),
        (KEY, 0o666, own, "mode 0666: readable and writable by its group and others"),
        (TOKEN, 0o600, own, None),
        (TOKEN, 0o640, own, None),  # the service's own group (0640 root:uav-swarm)
        (TOKEN, 0o440, own, None),
        (TOKEN, 0o640, other, "mode 0640: readable by its group "),
        (TOKEN, 0o660, own, "mode 0660: writable by its group"),
        (TOKEN, 0o644, own, "mode 0644: readable by others"),
        (TOKEN, 0o602, own, "mode 0602: writable by others"),
        (TOKEN, 0o601, own, "mode 0601: executable by others"),
    ]
    for policy, mode, gid, want in cases:
        path = _file(tmp_path, "f", "x", mode, gid)
        got = secret_file_problem(path, policy)
        if want is None:
            assert got is None, (policy, oct(mode), got)
        else:
            assert got is not None and got.startswith(f"{path}: {want}"), (policy, oct(mode), got)
            assert f"; fix: chmod 600 {path}" in got and got.count("\n") == 0, got
            if gid == other:
                assert f"(gid {other}), not this process's group " in got and "sudo -u" in got, got
    assert secret_file_problem(tmp_path / "missing", KEY) is None  # the reader says it is missing
    # a config without a secret: others may read it, nobody else may change it
    assert config_file_problem(_file(tmp_path, "c.toml", "x", 0o644)) is None
    got = config_file_problem(_file(tmp_path, "c.toml", "x", 0o646))
    assert (
        got is not None
        and "mode 0646: writable by others" in got
        and got.endswith("fix: chmod o-w " + str(tmp_path / "c.toml"))
    )
    got = config_file_problem(_file(tmp_path, "c.toml", "x", 0o664, other))
    assert got is not None and "writable by its group " in got and f"(gid {other}), not this" in got
    assert config_file_problem(_file(tmp_path, "c.toml", "x", 0o664, own)) is None


@pytest.mark.processes
def test_a_world_writable_config_stops_the_agent(tmp_path: Path) -> None:
    conf = _file(tmp_path, "agent.toml", 'name = "a1"\nid = 1\n', 0o666)
    done = _run(["agent", "--config", str(conf), *_zenoh()])
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{conf}: mode 0666: writable by others" in lines[0], lines
