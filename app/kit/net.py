"""Where the service may send requests of its own, and the one connection it sends them on.

Webhooks, e-mail alerts and schedule URL sources all go through :func:`check_url`: an http(s)
URL (no user name or password, at most :data:`MAX_URL_LENGTH` characters) whose host is
resolved and every address checked against :data:`REFUSED_ADDRESS_CLASSES`, unless the operator
allows private addresses (``SCANDIFF_ALLOW_PRIVATE_ADDRESSES=true``, one setting for every
caller).  :func:`pinned_connection` then connects to a checked address, never to the name again,
so a DNS answer that changes between check and use cannot redirect the request.
:class:`OutboundUrlError` (and :class:`RefusedAddressError` for an address in a refused class)
says what to fix.  No web, database or settings imports: callers pass the setting in.
"""

from __future__ import annotations

import http.client
import ipaddress
import re
import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import unquote, urlsplit

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address

ALLOWED_SCHEMES = ("http", "https")
MAX_URL_LENGTH = 2000
PRIVATE_ADDRESSES_SETTING = "SCANDIFF_ALLOW_PRIVATE_ADDRESSES"
PUBLIC_ONLY = (
    "outgoing requests go to public addresses only (the operator can allow private ones with "
    f"{PRIVATE_ADDRESSES_SETTING}=true)"
)
SHARED_ADDRESS_SPACE = ipaddress.IPv4Network("100.64.0.0/10")
"""Carrier-grade NAT (RFC 6598): neither private nor global."""


def _is_shared(address: IPAddress) -> bool:
    return isinstance(address, ipaddress.IPv4Address) and address in SHARED_ADDRESS_SPACE


REFUSED_ADDRESS_CLASSES: tuple[tuple[str, Callable[[IPAddress], bool]], ...] = (
    ("unspecified", lambda address: address.is_unspecified),
    ("loopback", lambda address: address.is_loopback),
    ("link-local", lambda address: address.is_link_local),
    ("multicast", lambda address: address.is_multicast),
    ("carrier-grade NAT", _is_shared),
    ("reserved", lambda address: address.is_reserved),
    ("private", lambda address: address.is_private),
    ("site-local", lambda address: getattr(address, "is_site_local", False)),
    ("non-global", lambda address: not address.is_global),
)
"""The address classes outgoing requests refuse, first match names it (an IPv4-mapped IPv6
address is judged as its IPv4 address).  ``private`` covers 10/8, 172.16/12, 192.168/16, the
IPv6 unique local fc00::/7 and the other special-purpose blocks Python's :mod:`ipaddress` calls
private (documentation, benchmarking, 192.0.0/24...); ``site-local`` is the deprecated IPv6
fec0::/10, which :mod:`ipaddress` calls global; ``non-global`` catches whatever else the IANA
registries do not mark globally reachable.  The list is documented in docs/webhooks.md."""


def refused_address_class(address: IPAddress) -> str | None:
    """The name of the refused class ``address`` belongs to; None for a public address."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    for name, belongs in REFUSED_ADDRESS_CLASSES:
        if belongs(address):
            return name
    return None


def address_is_public(address: IPAddress) -> bool:
    """Whether ``address`` is a global unicast address (in no refused class)."""
    return refused_address_class(address) is None


def resolved_addresses(host: str, port: int) -> list[IPAddress]:
    """Every address ``host`` resolves to (an IP literal is itself); OSError when none."""
    try:
        return [ipaddress.ip_address(host)]
    except ValueError:
        pass
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    return [ipaddress.ip_address(str(info[4][0]).split("%", 1)[0]) for info in infos]


class OutboundUrlError(ValueError):
    """A URL the service must not send requests to; the message says what to fix."""


class RefusedAddressError(OutboundUrlError):
    """A URL whose host is, or resolves to, an address in a refused class."""


@dataclass(frozen=True)
class UrlTarget:
    """A checked URL: where to connect (``addresses``, checked) and what to ask for."""

    scheme: str
    host: str
    port: int
    path: str
    addresses: tuple[str, ...]
    """The checked addresses (empty when not resolved); connect to one of these, not the name."""


def check_url(url: str, *, allow_private: bool, resolve: bool = True) -> UrlTarget:
    """``url`` checked for sending a request to; :class:`OutboundUrlError` says what is wrong.

    Parameters
    ----------
    url : str
        The absolute http(s) URL.
    allow_private : bool
        Accept addresses of the refused classes too (the operator's opt-out).
    resolve : bool
        Resolve a host name and check its addresses (False: check IP literals only).
    """
    if len(url) > MAX_URL_LENGTH:
        raise OutboundUrlError(f"the url is longer than {MAX_URL_LENGTH} characters")
    try:
        parts = urlsplit(url.strip())
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError as exc:
        raise OutboundUrlError(f"the url is malformed ({exc})") from exc
    if parts.scheme not in ALLOWED_SCHEMES:
        raise OutboundUrlError(
            f"the url's scheme must be http or https, not {parts.scheme or 'missing'!r} "
            "(example: https://hooks.example.com/scandiff)"
        )
    host = parts.hostname
    if not host:
        raise OutboundUrlError("the url has no host (example: https://hooks.example.com/scandiff)")
    if parts.username or parts.password:
        raise OutboundUrlError(
            "the url must not carry a user name or password; receivers check the signature"
        )
    path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
    if not allow_private and (host.lower() == "localhost" or host.lower().endswith(".localhost")):
        raise RefusedAddressError(f"{host} is a loopback address; {PUBLIC_ONLY}")
    addresses: list[IPAddress] = []
    if resolve or _is_ip_literal(host):
        try:
            addresses = resolved_addresses(host, port)
        except OSError as exc:
            raise OutboundUrlError(f"the host {host!r} cannot be resolved") from exc
        except ValueError as exc:
            raise OutboundUrlError(f"the host {host!r} resolves to no usable address") from exc
    if not allow_private:
        for address in addresses:
            refused = refused_address_class(address)
            if refused is not None:
                raise RefusedAddressError(
                    f"{host} is (or resolves to) the non-public address {address} ({refused}); "
                    f"{PUBLIC_ONLY}"
                )
    return UrlTarget(parts.scheme, host, port, path, tuple(str(address) for address in addresses))


def _is_ip_literal(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def pinned_connection(target: UrlTarget, timeout: float) -> http.client.HTTPConnection:
    """An HTTP(S) connection to ``target`` that connects to its first checked address.

    The request still names the host (``Host`` header, TLS server name and certificate check),
    but the socket goes to ``target.addresses[0]``, not to a new DNS answer.  A target checked
    without resolving (no addresses) connects to its host as given.
    """
    connection_class = (
        http.client.HTTPSConnection if target.scheme == "https" else http.client.HTTPConnection
    )
    connection = connection_class(target.host, target.port, timeout=timeout)
    if target.addresses:
        pinned = target.addresses[0]

        def connect_to_checked_address(
            address: tuple[str, int], timeout: float | None = None, source_address: Any = None
        ) -> socket.socket:
            return socket.create_connection((pinned, address[1]), timeout, source_address)

        connection._create_connection = connect_to_checked_address  # type: ignore[attr-defined]
    return connection


MAILTO_SCHEME = "mailto:"
MAX_RECIPIENTS = 10
_ADDRESS = re.compile(r"^[^@\s,<>()\[\]\\;:\"]+@[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?$")


def is_mailto(url: str) -> bool:
    """Whether ``url`` is an e-mail alert target (``mailto:a@example.com,b@example.com``)."""
    return url.strip().lower().startswith(MAILTO_SCHEME)


def mailto_recipients(url: str) -> list[str]:
    """The addresses of a ``mailto:`` URL; :class:`OutboundUrlError` says what is wrong."""
    text = url.strip()[len(MAILTO_SCHEME) :].split("?", 1)[0]
    addresses = [unquote(part).strip() for part in text.split(",") if part.strip()]
    if not addresses:
        raise OutboundUrlError("the mailto: url names no address (example: mailto:ops@example.com)")
    if len(addresses) > MAX_RECIPIENTS:
        raise OutboundUrlError(f"a mailto: url may name at most {MAX_RECIPIENTS} addresses")
    for address in addresses:
        if not _ADDRESS.match(address):
            raise OutboundUrlError(
                f"{address!r} is not an e-mail address (example: ops@example.com)"
            )
    return addresses
