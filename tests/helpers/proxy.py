"""A small TCP proxy to play a database outage without stopping the shared server.

:class:`TcpProxy` listens on a free loopback port and forwards every connection to ``target``
(threads, one pair per connection).  ``close()`` plays the outage: the listening socket goes
away (new connections are refused) and every open connection is cut (the server "went away").
``open()`` listens again on the same port: the service must recover by itself.
"""

from __future__ import annotations

import contextlib
import socket
import threading

from app.testing.network import free_port

CHUNK_BYTES = 65536


class TcpProxy:
    """Forward ``127.0.0.1:<port>`` to ``target`` until closed; reopen on the same port."""

    def __init__(self, target: tuple[str, int], port: int | None = None) -> None:
        self.target = target
        self.port = port or free_port()
        self._listener: socket.socket | None = None
        self._accepting: threading.Thread | None = None
        self._connections: set[socket.socket] = set()
        self._lock = threading.Lock()
        self.connections_made = 0

    def open(self) -> TcpProxy:
        """Start listening (again) on :attr:`port`."""
        if self._listener is not None:
            raise RuntimeError("proxy already open")
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(64)
        self._listener = listener
        self._accepting = threading.Thread(target=self._accept, args=(listener,), daemon=True)
        self._accepting.start()
        return self

    def close(self) -> None:
        """Refuse new connections and cut every open one (an outage)."""
        listener, self._listener = self._listener, None
        if listener is not None:
            with contextlib.suppress(OSError):
                listener.shutdown(socket.SHUT_RDWR)
            listener.close()
        if self._accepting is not None:
            self._accepting.join(timeout=5)
            self._accepting = None
        with self._lock:
            connections, self._connections = self._connections, set()
        for connection in connections:
            with contextlib.suppress(OSError):
                connection.shutdown(socket.SHUT_RDWR)
            connection.close()

    @property
    def is_open(self) -> bool:
        """Whether the proxy accepts connections."""
        return self._listener is not None

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _address = listener.accept()
            except OSError:
                return  # closed
            try:
                upstream = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            upstream.settimeout(None)
            with self._lock:
                if self._listener is not listener:  # closed meanwhile
                    client.close()
                    upstream.close()
                    return
                self._connections.update((client, upstream))
                self.connections_made += 1
            for source, sink in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(source, sink), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(CHUNK_BYTES):
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for end in (source, sink):
                with contextlib.suppress(OSError):
                    end.shutdown(socket.SHUT_RDWR)
            with self._lock:
                self._connections.discard(source)
                self._connections.discard(sink)

    def __enter__(self) -> TcpProxy:
        return self if self.is_open else self.open()

    def __exit__(self, *exc_info: object) -> None:
        self.close()
