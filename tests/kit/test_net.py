"""The outgoing-URL rule on its own: the opt-out accepts every class, the URL's shape is
checked, the pinned connection goes to the checked address, and the old setting names work."""

from __future__ import annotations

import ipaddress
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from app.config import Settings
from app.kit.net import (
    OutboundUrlError,
    RefusedAddressError,
    check_url,
    pinned_connection,
)
from tests.helpers.addresses import REFUSED_HOSTS


@pytest.mark.parametrize(("host", "address_class"), REFUSED_HOSTS)
def test_the_operator_opt_out_accepts_every_class(host: str, address_class: str) -> None:
    with pytest.raises(RefusedAddressError, match=rf"\({address_class}\)"):
        check_url(f"http://{host}/hook", allow_private=False)
    target = check_url(f"http://{host}/hook", allow_private=True)
    assert target.addresses == (str(ipaddress.ip_address(host.strip("[]"))),)


@pytest.mark.parametrize(
    ("url", "fragment"),
    [
        ("ftp://93.184.215.14/x", "scheme must be http or https"),
        ("https:///x", "no host"),
        ("https://user:secret@93.184.215.14/x", "user name or password"),
        ("https://93.184.215.14/" + "x" * 2000, "longer than 2000"),
        ("https://93.184.215.14:99999/x", "malformed"),
    ],
)
def test_a_malformed_url_is_refused_saying_why(url: str, fragment: str) -> None:
    with pytest.raises(OutboundUrlError, match=fragment) as refused:
        check_url(url, allow_private=True)
    assert not isinstance(refused.value, RefusedAddressError)


class _Answer(BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        body = self.headers["Host"].encode()
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        return


def test_the_pinned_connection_goes_to_the_checked_address_under_the_given_name() -> None:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Answer)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        port = server.server_address[1]
        target = check_url(f"http://127.0.0.1:{port}/x", allow_private=True)
        # A name that would resolve elsewhere (nowhere): the socket still goes to the address.
        renamed = type(target)("http", "receiver.invalid", port, "/x", target.addresses)
        connection = pinned_connection(renamed, timeout=5.0)
        try:
            connection.request("GET", renamed.path)
            response = connection.getresponse()
            assert response.status == 200
            assert response.read() == f"receiver.invalid:{port}".encode()
        finally:
            connection.close()
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize(
    "variable",
    [
        "SCANDIFF_ALLOW_PRIVATE_ADDRESSES",
        "SCANDIFF_WEBHOOK_ALLOW_PRIVATE_ADDRESSES",
        "SCANDIFF_SCHEDULE_ALLOW_PRIVATE_URLS",
    ],
)
def test_one_setting_with_its_deprecated_names(
    variable: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert Settings().allow_private_addresses is False
    monkeypatch.setenv(variable, "true")
    assert Settings().allow_private_addresses is True
    assert Settings(allow_private_addresses=False).allow_private_addresses is False
