"""Hosts of every address class the service's own requests refuse, and public ones
(IP literals, so no DNS is involved): the cases of the outgoing-URL rule's tests."""

from __future__ import annotations

REFUSED_HOSTS: tuple[tuple[str, str], ...] = (
    ("0.0.0.0", "unspecified"),
    ("[::]", "unspecified"),
    ("127.0.0.1", "loopback"),
    ("[::1]", "loopback"),
    ("169.254.169.254", "link-local"),
    ("[fe80::1]", "link-local"),
    ("224.0.0.1", "multicast"),
    ("[ff02::1]", "multicast"),
    ("100.64.0.1", "carrier-grade NAT"),
    ("100.127.255.254", "carrier-grade NAT"),
    ("240.0.0.1", "reserved"),
    ("[64:ff9b::7f00:1]", "reserved"),
    ("10.1.2.3", "private"),
    ("172.16.0.1", "private"),
    ("192.168.0.10", "private"),
    ("192.0.2.1", "private"),
    ("198.18.0.1", "private"),
    ("[fd00::1]", "private"),
    ("[fec0::1]", "site-local"),
    ("[::ffff:127.0.0.1]", "loopback"),
    ("[::ffff:10.0.0.1]", "private"),
    ("[::ffff:100.64.0.1]", "carrier-grade NAT"),
)
"""A host of every refused class (IPv4, IPv6 and IPv4-mapped forms) and the class named."""

PUBLIC_HOSTS = ("93.184.215.14", "[2606:4700:4700::1111]")
"""Global unicast addresses (IPv4 and IPv6): accepted, never connected to by the tests."""
