"""Loopback checks that parse addresses instead of comparing strings.

`is_loopback("127.0.0.1.nip.io")` is False: a name is accepted only from the fixed list `LOOPBACK_NAMES`, never
resolved through DNS (a resolver answer can change between the check and the connection: DNS rebinding).
"""

from __future__ import annotations

import ipaddress

#: Host names taken as loopback without a DNS lookup (compared case-insensitively, trailing dot ignored).
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})


def is_loopback(host: str) -> bool:
    """True when `host` is a loopback address (127.0.0.0/8, ::1, IPv4-mapped ::ffff:127.x) or a fixed loopback name.

    Accepts an optional pair of brackets around an IPv6 address ("[::1]"); no port (see `host_header_is_loopback`).
    """
    text = host.strip()
    if text.startswith("[") and text.endswith("]"):
        text = text[1:-1]
    if not text:
        return False
    name = text.lower().rstrip(".")
    if name in LOOPBACK_NAMES:
        return True
    if "%" in name:  # scoped IPv6 (fe80::1%eth0) is never loopback; ::1 has no scope
        return False
    try:
        addr = ipaddress.ip_address(name)
    except ValueError:
        return False
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        return addr.ipv4_mapped.is_loopback
    return addr.is_loopback


def host_header_is_loopback(value: str | None) -> bool:
    """True when an HTTP Host header names a loopback host, with an optional decimal port (1..65535).

    Examples: "127.0.0.1:8765", "localhost", "[::1]:80" pass; "evil.example", "127.0.0.1.nip.io:80", "" fail.
    """
    if value is None:
        return False
    text = value.strip()
    if not text or any(c.isspace() for c in text):
        return False
    host, port = text, ""
    if text.startswith("["):
        end = text.find("]")
        if end < 0:
            return False
        host, rest = text[: end + 1], text[end + 1 :]
        if rest:
            if not rest.startswith(":"):
                return False
            port = rest[1:]
    elif text.count(":") == 1:
        host, port = text.split(":")
    elif ":" in text:  # a bare IPv6 address without brackets is not a valid Host header
        return False
    has_port = bool(port) or text.endswith(":")
    if has_port and not (port.isascii() and port.isdigit() and 0 < int(port) < 65536):
        return False
    return is_loopback(host)


def is_ipv4_loopback_literal(host: str) -> bool:
    """True only for an IPv4 address literal in 127.0.0.0/8 (what a server binding an IPv4 socket may take);
    names, '127.0.0.1.nip.io' and IPv6 are refused."""
    try:
        return ipaddress.IPv4Address(host.strip()).is_loopback
    except ValueError:
        return False
