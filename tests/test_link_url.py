"""The one URL grammar (radios.url) and the backend registry (radios.link).

The grammar is pure: each form parses to a scheme, a target and options, and a
malformed string raises LinkOpenError with the string in the message. The
registry imports a backend only when a URL names it, and no backend imports the
factory (a fresh interpreter shows which modules an import pulled in).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from radios.errors import LinkOpenError
from radios.link import BACKENDS, SCHEMES, backend, open_link
from radios.linkbase import Link
from radios.url import Endpoint, LinkURL, Options, parse_endpoint, parse_link_url

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    ("url", "scheme", "target", "options"),
    [
        ("/dev/ttyUSB0", "serial", "/dev/ttyUSB0", {}),
        ("/dev/ttyUSB0?baud=57600", "serial", "/dev/ttyUSB0", {"baud": "57600"}),
        ("radios/radio0", "serial", "radios/radio0", {}),
        ("COM3?baud=115200", "serial", "COM3", {"baud": "115200"}),
        ("serial:/dev/x?baud=9600&rtscts=1", "serial", "/dev/x", {"baud": "9600", "rtscts": "1"}),
        ("serial:///dev/x", "serial", "/dev/x", {}),
        ("SERIAL:/dev/x", "serial", "/dev/x", {}),
        ("serial:", "serial", "", {}),
        ("serial:/dev/x.tlog", "serial", "/dev/x.tlog", {}),  # an explicit scheme wins
        ("loop://", "loop", "loop://", {}),
        ("loop://?baud=x", "loop", "loop://", {"baud": "x"}),
        ("socket://localhost:7000", "socket", "socket://localhost:7000", {}),
        ("tlog:flight.tlog?speed=2&max_gap=inf", "tlog", "flight.tlog", {"speed": "2", "max_gap": "inf"}),
        ("tlog://dir/f.tlog", "tlog", "dir/f.tlog", {}),
        ("tlog:", "tlog", "", {}),
        ("caps/flight.tlog?speed=0", "tlog", "caps/flight.tlog", {"speed": "0"}),
        ("virtual://bench?loss=0.25&seed=3", "virtual", "bench", {"loss": "0.25", "seed": "3"}),
        ("virtual:bench", "virtual", "bench", {}),
        ("virtual://", "virtual", "", {}),
        ("foo://x", "foo", "x", {}),
        ("foo:bar", "foo", "bar", {}),
        ("1:x", "1", "1:x", {}),
        ("/dev/x?flag", "serial", "/dev/x", {"flag": ""}),
    ],
)
def test_link_url_forms(url: str, scheme: str, target: str, options: dict[str, str]) -> None:
    parsed = parse_link_url(url)
    assert parsed == LinkURL(url, scheme, target, options)


@pytest.mark.parametrize("url", ["", None, 7, b"/dev/x"])
def test_empty_or_not_a_string(url: object) -> None:
    with pytest.raises(LinkOpenError, match="empty link URL"):
        parse_link_url(url)  # type: ignore[arg-type]


def test_a_nul_character_is_refused_by_every_backend_in_one_line(tmp_path: Path) -> None:
    """A NUL reached open() and escaped as a ValueError traceback for captures."""
    for url in ("x\x00.tlog", "tlog:\x00.tlog", "/dev/tty\x00", "virtual://a\x00b", "loop://\x00"):
        with pytest.raises(LinkOpenError, match="cannot contain a NUL character") as info:
            open_link(url)
        assert "\n" not in str(info.value)


def test_options_are_read_typed_and_leftovers_refused() -> None:
    opts = Options(parse_link_url("/dev/x?baud=9600&wt=0.5&bogus=1&zz=2"))
    assert opts.integer("baud", 1) == 9600
    assert opts.integer("missing", 42) == 42
    assert opts.number("wt", 2.0) == 0.5
    with pytest.raises(LinkOpenError, match=r"^/dev/x\?.*: unknown option\(s\) bogus, zz \(known: a, b\)$"):
        opts.finish(("a", "b"))
    for query, message in [("n=1.5", "n must be an integer"), ("n=", "n must be an integer")]:
        with pytest.raises(LinkOpenError, match=message):
            Options(parse_link_url(f"/x?{query}")).integer("n", 0)
    with pytest.raises(LinkOpenError, match="f must be a number"):
        Options(parse_link_url("/x?f=fast")).number("f", 0.0)


# -- the flight-controller forms --------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("serial:/dev/ttyAMA0:921600", Endpoint("serial", device="/dev/ttyAMA0", baud=921600)),
        ("serial:/dev/ttyUSB0", Endpoint("serial", device="/dev/ttyUSB0", baud=57600)),
        ("/dev/ttyACM0:115200", Endpoint("serial", device="/dev/ttyACM0", baud=115200)),
        ("udp:127.0.0.1:14540", Endpoint("udpin", host="127.0.0.1", port=14540)),
        ("udpin:0.0.0.0:14541", Endpoint("udpin", host="0.0.0.0", port=14541)),
        ("udp://:14540", Endpoint("udpin", host="0.0.0.0", port=14540)),
        ("udpout:10.0.0.2:14550", Endpoint("udpout", host="10.0.0.2", port=14550)),
        ("tcp:127.0.0.1:5760", Endpoint("tcp", host="127.0.0.1", port=5760)),
        ("TCP:[::1]:5760", Endpoint("tcp", host="::1", port=5760)),
    ],
)
def test_endpoint_forms(url: str, expected: Endpoint) -> None:
    assert parse_endpoint(url) == expected
    assert parse_endpoint(str(expected)) == expected


def test_endpoint_default_baud() -> None:
    assert parse_endpoint("/dev/ttyS1", default_baud=921600).baud == 921600


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("", "empty"),
        ("   ", "empty"),
        ("nonsense", "expected SCHEME"),
        ("ftp:host:21", "unknown scheme 'ftp'"),
        ("udp:127.0.0.1", "expected udp:HOST:PORT"),
        ("udp:127.0.0.1:port", "not a number"),
        ("udp:127.0.0.1:0", "out of range"),
        ("udp:127.0.0.1:70000", "out of range"),
        ("tcp::5760", "needs a host"),
        ("tcp:127.0.0.1", "expected tcp:HOST:PORT"),
        ("serial:", "expected SCHEME"),
        ("serial:/dev/ttyS0:fast", "not a number"),
        ("serial:/dev/ttyS0:-5", "must be positive"),
        ("serial::57600", "no serial device"),
        ("udpout::14550", "needs a host"),
    ],
)
def test_endpoint_rejects(url: str, message: str) -> None:
    with pytest.raises(LinkOpenError, match=message):
        parse_endpoint(url)


# -- the registry -----------------------------------------------------------------------------


def test_registry_is_read_only_and_every_backend_resolves() -> None:
    with pytest.raises(TypeError):
        BACKENDS["mine"] = "tests:nothing"  # type: ignore[index]
    for scheme in BACKENDS:
        assert callable(backend(scheme))
    written = {s.split(":", 1)[0] for s in SCHEMES}
    assert written == set(BACKENDS)


def test_unknown_scheme_names_the_known_ones() -> None:
    for url in ("foo://x", "foo:bar", "udpin:1.2.3.4:5"):
        with pytest.raises(LinkOpenError) as info:
            open_link(url)
        message = str(info.value)
        assert "\n" not in message and message.startswith(url)
        assert "unknown link scheme" in message
        for scheme in SCHEMES:
            assert scheme in message


def test_pyserial_scheme_without_slashes_is_refused() -> None:
    with pytest.raises(LinkOpenError, match=r"loop:x: a pyserial URL is written loop://"):
        open_link("loop:x")


def _imported_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"import sys\n{code}\nprint(' '.join(sorted(sys.modules)))"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    return set(out.split())


def test_backends_are_imported_lazily_and_never_import_the_factory() -> None:
    """No import circle: the factory pulls in no backend until a URL names it, and the
    backends, the grammar and the capture wrapper do not pull in the factory."""
    after_factory = _imported_after("import radios.link")
    assert not {"radios.replay", "radios.virtual", "radios.seriallink"} & after_factory
    after_backends = _imported_after(
        "import radios.seriallink, radios.virtual, radios.replay, radios.capture, radios.url"
    )
    assert "radios.link" not in after_backends
    after_open = _imported_after("import radios.link\nradios.link.open_link('virtual://x').close()")
    assert "radios.virtual" in after_open and "radios.replay" not in after_open


def test_open_link_returns_links_of_each_backend(tmp_path: Path) -> None:
    with open_link("virtual://registry-test") as link:
        assert isinstance(link, Link) and type(link).__name__ == "VirtualLink"
    with open_link("loop://") as link:
        assert type(link).__name__ == "SerialLink"
