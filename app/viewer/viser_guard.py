"""The one adapter over viser's internals: a per-view secret its websocket must present.

viser binds its server with ``websockets.asyncio.server.serve(host, port)`` and has no hook to
authenticate a connection (nor to bind a Unix socket), so anyone on the host could open the
loopback port and receive the scene.  :func:`require_view_secret` closes every websocket whose
opening handshake lacks ``X-Scandiff-View-Secret: <secret>`` before viser sends it anything.

It relies on two things viser 1.1 does (checked by ``tests/browser/test_viewer_port_security.py``):

* ``ViserServer._websock_server`` is the :class:`viser.infra.WebsockServer`, whose
  ``_live_connections`` maps a client id to its ``websockets`` ``ServerConnection`` (with the
  handshake ``request``) before the connect callbacks run;
* the connection's message producers start only after every connect callback has returned,
  so a connection closed in a callback is sent nothing.

viser starts listening inside ``ViserServer()``, a moment before the check is installed: the
check then closes (and waits for) any connection already open, so call it before the scene is
added or any connect callback that sends scan data is registered.

:func:`require_view_secret` raises :class:`ViserInternalsChangedError` at once when the
attributes are gone, and a callback that cannot find its connection refuses it (fails closed).
"""

from __future__ import annotations

import asyncio
import hmac
import logging
from typing import Any

import viser
import viser.infra

logger = logging.getLogger("scandiff.viewer")

VIEW_SECRET_HEADER = "X-Scandiff-View-Secret"
"""The header the API's proxy sends to its viser server with the view's secret."""

WEBSOCKET_POLICY_VIOLATION = 1008
REFUSAL_REASON = "the view secret is missing or wrong"


class ViserInternalsChangedError(RuntimeError):
    """viser no longer has what :func:`require_view_secret` relies on: check the adapter."""


def _websock_server(server: viser.ViserServer) -> viser.infra.WebsockServer:
    """viser's websocket server behind ``server``, checked to have the live-connection map."""
    websock = getattr(server, "_websock_server", None)
    if (
        not isinstance(websock, viser.infra.WebsockServer)
        or not isinstance(getattr(websock, "_live_connections", None), dict)
        or not isinstance(
            getattr(websock, "_background_event_loop", None), asyncio.AbstractEventLoop
        )
    ):
        raise ViserInternalsChangedError(
            f"viser {viser.__version__} has no ViserServer._websock_server._live_connections "
            "or _background_event_loop: "
            "app/viewer/viser_guard.py cannot check the view secret (pin viser to a tested "
            "version in pyproject.toml or adapt the guard)"
        )
    return websock


def presented_secret(connection: Any) -> str:
    """The view secret in a ``websockets`` server connection's handshake ('' when absent)."""
    request = getattr(connection, "request", None)
    headers = getattr(request, "headers", None)
    return str(headers.get(VIEW_SECRET_HEADER, "")) if headers is not None else ""


class ViewSecretCheck:
    """The check installed on one viser server; which of its clients it refused."""

    def __init__(self) -> None:
        self._refused: set[int] = set()

    def refused(self, client_id: int) -> bool:
        """Whether the client was closed for lacking the secret (skip building its scene:
        viser may still hand on a message it buffered before the close)."""
        return client_id in self._refused


def require_view_secret(
    server: viser.ViserServer, secret: str, *, timeout: float = 15.0
) -> ViewSecretCheck:
    """Close, before viser sends a byte, every websocket to ``server`` without ``secret``.

    Connections opened before the call that lack the secret are closed before it returns.

    Raises
    ------
    ViserInternalsChangedError
        This viser lacks the internals the check hooks into.
    """
    if not secret:
        raise ValueError("a view secret must not be empty")
    websock = _websock_server(server)
    live: dict[int, Any] = websock._live_connections
    expected = secret.encode()
    check = ViewSecretCheck()

    def has_secret(connection: Any) -> bool:
        return hmac.compare_digest(presented_secret(connection).encode(), expected)

    @websock.on_client_connect
    async def check_secret(client: viser.infra.WebsockClientConnection) -> None:
        connection = live.get(client.client_id)
        if connection is None:
            logger.error(
                "viser's live connection of client %s is missing: refusing it "
                "(app/viewer/viser_guard.py needs adapting to viser %s)",
                client.client_id,
                viser.__version__,
            )
            check._refused.add(client.client_id)
            raise ViserInternalsChangedError("viser's live connection map changed")
        if has_secret(connection):
            return
        check._refused.add(client.client_id)
        logger.warning("refused a websocket to a viser server without the view secret")
        await connection.close(WEBSOCKET_POLICY_VIOLATION, REFUSAL_REASON)

    @websock.on_client_disconnect
    def forget(client: viser.infra.WebsockClientConnection) -> None:
        check._refused.discard(client.client_id)

    loop = websock._background_event_loop
    already_open = {
        client_id: connection
        for client_id, connection in list(live.items())
        if not has_secret(connection)
    }
    check._refused.update(already_open)
    for connection in already_open.values():
        logger.warning("closed a websocket opened before the view secret was required")
        closing = asyncio.run_coroutine_threadsafe(
            connection.close(WEBSOCKET_POLICY_VIOLATION, REFUSAL_REASON), loop
        )
        closing.result(timeout)
    return check
