"""Zenoh's errors in one line a user understands: its own sentence, without the Rust
debug wrapping or the source paths of the Zenoh build. Pure text functions."""

from __future__ import annotations

import re
from collections.abc import Sequence

#: Zenoh's errors end with where in its Rust source they were raised: " at /root/.cargo/...rs:61."
RUST_SOURCE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_BOUND_TO = re.compile(r"bound to ([a-z]+/\S+?):\s")


_JSON5_MSG = re.compile(r'msg: "(.*?)"(?:, location|\s*\})')


def zenoh_config_message(text: str) -> str:
    """One line for Zenoh's refusal of an endpoint: its own sentence, without the
    Rust debug wrapping (``Json5Err(Message { msg: ...``) or source paths."""
    m = _JSON5_MSG.search(text)
    detail = RUST_SOURCE.sub("", m.group(1) if m else text).strip().rstrip(".")
    return f"bad Zenoh endpoint: {detail} (for example tcp/127.0.0.1:7447)"


def zenoh_open_message(text: str, listen: Sequence[str], connect: Sequence[str]) -> str:
    """One line a user understands for Zenoh's ``zenoh.open`` error ``text``: a port in
    use or an address not of this machine named as such, and never the Rust source
    paths of the Zenoh build."""
    m = _BOUND_TO.search(text)
    endpoint = m.group(1) if m else (listen[0] if len(listen) == 1 else "")
    port = endpoint.rpartition(":")[2]
    if "Address already in use" in text and endpoint:
        return f"cannot listen on {endpoint}: port {port} in use (another program, or another swarm node?)"
    if "Cannot assign requested address" in text and endpoint:
        return f"cannot listen on {endpoint}: that address is not one of this machine's"
    detail = RUST_SOURCE.sub("", text).replace("[", "").replace("]", "").strip().rstrip(".")
    where = "; ".join(f"{k} {' '.join(v)}" for k, v in (("listen", listen), ("connect", connect)) if v)
    return f"cannot open Zenoh session ({where or 'no endpoints'}): {detail}"
