"""Where the service may send requests of its own (webhooks): http(s) URLs to public addresses.

:func:`check_outbound_url` checks a URL and resolves its host (:class:`OutboundUrlError` says
what is wrong); the caller connects to the checked addresses, not to the name again (no DNS
rebinding between check and use).  Loopback, private, link-local, multicast, reserved and
unspecified addresses are refused unless the operator allows them (a receiver on the same host
or network).  No web, database or settings imports.
"""

from __future__ import annotations

import ipaddress
import re
import socket
from dataclasses import dataclass
from urllib.parse import unquote, urlsplit

ALLOWED_SCHEMES = ("http", "https")
MAX_URL_LENGTH = 2000
PUBLIC_ONLY = (
    "webhooks go to public addresses only (the operator can allow private ones with "
    "SCANDIFF_WEBHOOK_ALLOW_PRIVATE_ADDRESSES=true)"
)


def address_is_public(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """Whether ``address`` is a global unicast address (not loopback, private, link-local...)."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_global and not address.is_multicast


def resolved_addresses(host: str, port: int) -> list[ipaddress.IPv4Address | ipaddress.IPv6Address]:
    """Every address ``host`` resolves to (an IP literal is itself); OSError when none."""
    try:
        return [ipaddress.ip_address(host)]
    except ValueError:
        pass
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    return [ipaddress.ip_address(info[4][0].split("%", 1)[0]) for info in infos]


class OutboundUrlError(ValueError):
    """A URL the service must not send requests to; the message says what to fix."""


@dataclass(frozen=True)
class OutboundTarget:
    """A checked URL: where to connect (``addresses``, checked) and what to ask for."""

    scheme: str
    host: str
    port: int
    path: str
    addresses: tuple[str, ...]
    """The checked addresses (empty when not resolved); connect to one of these, not the name."""


def check_outbound_url(url: str, *, allow_private: bool, resolve: bool = True) -> OutboundTarget:
    """``url`` checked for sending a request to; :class:`OutboundUrlError` says what is wrong.

    Parameters
    ----------
    url : str
        The absolute http(s) URL.
    allow_private : bool
        Accept loopback, private and other non-public addresses too.
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
        raise OutboundUrlError(f"{host} is a loopback address; {PUBLIC_ONLY}")
    addresses: list[ipaddress.IPv4Address | ipaddress.IPv6Address] = []
    if resolve or _is_ip_literal(host):
        try:
            addresses = resolved_addresses(host, port)
        except OSError as exc:
            raise OutboundUrlError(f"the host {host!r} cannot be resolved") from exc
        except ValueError as exc:
            raise OutboundUrlError(f"the host {host!r} resolves to no usable address") from exc
    if not allow_private:
        for address in addresses:
            if not address_is_public(address):
                raise OutboundUrlError(
                    f"{host} is (or resolves to) the non-public address {address}; {PUBLIC_ONLY}"
                )
    return OutboundTarget(
        parts.scheme, host, port, path, tuple(str(address) for address in addresses)
    )


def _is_ip_literal(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


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
