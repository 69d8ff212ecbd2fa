"""Outbound requests to user-given URLs (webhooks) without server-side request forgery.

A URL's host is resolved when the request is made, and the request is refused before any connection
when one of its addresses is not a public unicast address: loopback, private (RFC 1918, unique local),
link-local (cloud metadata at 169.254.169.254), multicast, unspecified, reserved, shared (100.64/10),
documentation and benchmarking ranges, in IPv4 and IPv6, IPv4-mapped and NAT64/6to4/Teredo forms
included, whatever the encoding of the host (`0x7f000001`, `2130706433`, `0177.0.0.1`, `127.1`,
`[::ffff:127.0.0.1]`). The request then connects to the address that was checked (no second lookup
that DNS rebinding could answer differently), with the original Host header and TLS server name.
Redirects are never followed. An operator allow-list (CIDR networks, `MIDVIEW_WEBHOOK_ALLOW_NETWORKS`)
admits chosen internal receivers.
"""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from urllib.parse import urlsplit, urlunsplit

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
Resolver = Callable[[str, int], list[str]]

LOCAL_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback")


class BlockedURL(ValueError):
    """A URL that outbound requests may not reach; the message says why."""


@dataclass(frozen=True)
class Target:
    """A checked URL: the address to connect to and what the request must carry for the host."""

    url: str  # the original URL
    host: str
    port: int
    address: str  # the checked IP address
    pinned_url: str  # the URL with the address in place of the host

    @property
    def tls(self) -> bool:
        return self.url.lower().startswith("https:")


def parse_networks(spec: str | Iterable[str] | None) -> list[IPNetwork]:
    """CIDR networks of a comma-separated string or a list ("127.0.0.1/32, 10.1.0.0/16")."""
    if not spec:
        return []
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    out = []
    for item in items:
        item = item.strip()
        if item:
            try:
                out.append(ipaddress.ip_network(item, strict=False))
            except ValueError as e:
                raise ValueError(f"not a CIDR network: {item!r} ({e})") from e
    return out


def literal_address(host: str) -> IPAddress | None:
    """The IP address a host names literally, in any encoding inet_aton accepts (decimal, hex, octal,
    shortened IPv4), or None for a host name."""
    h = host.strip().strip("[]").rstrip(".")
    try:
        return ipaddress.ip_address(h.split("%", 1)[0])
    except ValueError:
        pass
    try:
        return ipaddress.IPv4Address(socket.inet_aton(h))
    except (OSError, ValueError):
        return None


def _embedded_ipv4(addr: IPAddress) -> IPAddress | None:
    """The IPv4 address inside an IPv4-mapped, IPv4-compatible, NAT64, 6to4 or Teredo IPv6 address."""
    if not isinstance(addr, ipaddress.IPv6Address):
        return None
    if addr.ipv4_mapped is not None:
        return addr.ipv4_mapped
    if addr.sixtofour is not None:
        return addr.sixtofour
    if addr.teredo is not None:
        return addr.teredo[1]
    packed = addr.packed
    if packed[:12] == b"\0" * 12 and packed[12:] != b"\0\0\0\0":  # ::a.b.c.d (deprecated compatible)
        return ipaddress.IPv4Address(packed[12:])
    if addr in ipaddress.ip_network("64:ff9b::/96") or addr in ipaddress.ip_network("64:ff9b:1::/48"):
        return ipaddress.IPv4Address(packed[12:])
    return None


def refusal(addr: IPAddress) -> str | None:
    """Why an address may not be reached (None: a public unicast address)."""
    for label, test in (
        ("loopback", addr.is_loopback),
        ("unspecified", addr.is_unspecified),
        ("link-local", addr.is_link_local),
        ("multicast", addr.is_multicast),
        ("private", addr.is_private),
        ("reserved", addr.is_reserved),
    ):
        if test:
            return f"{label} address {addr}"
    if not addr.is_global:
        return f"non-public address {addr}"
    inner = _embedded_ipv4(addr)
    if inner is not None:
        why = refusal(inner)
        return f"{why} (inside {addr})" if why else None
    return None


def check_address(addr: IPAddress, allow: list[IPNetwork]) -> None:
    """Raise BlockedURL unless the address is public or inside an allowed network."""
    if any(addr.version == n.version and addr in n for n in allow):
        return
    why = refusal(addr)
    if why:
        raise BlockedURL(f"refused: {why}")


def split_url(url: str) -> tuple[str, str, int]:
    """(scheme, host, port) of an http(s) URL; BlockedURL for anything else."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as e:
        raise BlockedURL(f"not a valid URL: {e}") from e
    scheme = parts.scheme.lower()
    if scheme not in ("http", "https"):
        raise BlockedURL(f"scheme {scheme or '(none)'!r} is not allowed (http or https)")
    if not parts.hostname:
        raise BlockedURL("the URL has no host")
    if parts.username or parts.password:
        raise BlockedURL("credentials in the URL are not allowed")
    return scheme, parts.hostname, port or (443 if scheme == "https" else 80)


def check_literal(url: str, allow: list[IPNetwork] | None = None) -> None:
    """What can be checked without a DNS lookup (when a URL is registered): scheme, credentials, a
    literal address in any encoding, local names. Raises BlockedURL."""
    _, host, _ = split_url(url)
    name = host.lower().rstrip(".")
    addr = literal_address(name)
    if addr is not None:
        check_address(addr, allow or [])
    elif name in LOCAL_NAMES or name.endswith(".localhost"):
        if not any(n.version == 4 and ipaddress.ip_address("127.0.0.1") in n for n in allow or []):
            raise BlockedURL(f"refused: {host} is a local name")


def system_resolver(host: str, port: int) -> list[str]:
    """Every address the system resolver gives for host (IPv4 and IPv6)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise BlockedURL(f"cannot resolve {host}: {e}") from e
    return list(dict.fromkeys(str(i[4][0]) for i in infos))


def check_registration(
    url: str, allow: list[IPNetwork] | None = None, resolver: Resolver | None = None
) -> None:
    """check_literal, and every address the URL's host resolves to now (a host name pointing at loopback
    or a private network is refused when it is registered, not only at delivery). A name that does not
    resolve yet is left to the check at every delivery. Raises BlockedURL."""
    check_literal(url, allow)
    _, host, port = split_url(url)
    if literal_address(host) is not None:
        return
    try:
        addresses = (resolver or system_resolver)(host, port)
    except BlockedURL:
        return
    for a in addresses:
        check_address(ipaddress.ip_address(a.split("%", 1)[0]), allow or [])


def resolve(url: str, allow: list[IPNetwork] | None = None, resolver: Resolver = system_resolver) -> Target:
    """Resolve a URL's host and check every address it resolves to; the Target connects to the first.

    Raises BlockedURL (before any connection) when the URL is not http(s) or any address is refused."""
    check_literal(url, allow)
    scheme, host, port = split_url(url)
    addr = literal_address(host)
    addresses = [str(addr)] if addr is not None else resolver(host, port)
    if not addresses:
        raise BlockedURL(f"{host} resolves to no address")
    for a in addresses:
        check_address(ipaddress.ip_address(a.split("%", 1)[0]), allow or [])
    first = ipaddress.ip_address(addresses[0].split("%", 1)[0])
    netloc = (f"[{first}]" if first.version == 6 else str(first)) + f":{port}"
    parts = urlsplit(url)
    pinned = urlunsplit((scheme, netloc, parts.path, parts.query, ""))
    return Target(url, host, port, str(first), pinned)


def pinned_request_args(target: Target) -> dict:
    """httpx request arguments that send to the checked address with the original Host and TLS name."""
    default = 443 if target.tls else 80
    host = target.host if target.port == default else f"{target.host}:{target.port}"
    extensions = {"sni_hostname": target.host} if target.tls else {}
    return {"url": target.pinned_url, "headers": {"Host": host}, "extensions": extensions}
