"""What the project's two HTTP servers share (the diagnosis server, labrobfail_vlm/serve/cli.py, and the policy
server, sim_backends/policies/server.py): binding before anything heavy loads, the bearer token from the
environment, uvicorn's graceful stop, and the app's own log lines."""

from __future__ import annotations

import ipaddress
import logging
import os
import signal
import socket
import sys
from typing import Any

from labrobfail_vlm.config import ConfigError


def loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def listen(host: str, port: int) -> socket.socket:
    """A listening socket: a taken port fails at start, in one line, before any model or policy is loaded."""
    try:
        sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(2048)  # connections made before uvicorn starts wait in the backlog instead of being refused
    except (OSError, OverflowError) as e:
        raise ConfigError(f"host/port: cannot listen on {host}:{port} ({getattr(e, 'strerror', None) or e})") from None
    return sock


def bearer_token(env: str, host: str) -> str | None:
    """The token from the variable `env` names (never logged); a warning when serving beyond loopback without one."""
    token = os.environ.get(env, "")
    if not loopback(host) and not token:
        print(f"warning: serving on {host} without a token; set {env} to require one", file=sys.stderr)
    return token or None


def app_log(name: str, level: str) -> None:
    """The app's own lines (a client gone mid-upload, an internal error) in uvicorn's format, one line each."""
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s:  %(message)s"))
    lg = logging.getLogger(name)
    lg.addHandler(handler)
    lg.setLevel(level.upper())
    lg.propagate = False


def head_timeout_protocol(seconds: float) -> type:
    """uvicorn's h11 protocol, closing a connection whose request head has not arrived `seconds` after it was
    opened or after its previous response. uvicorn times out an idle connection only after a response and stops
    that clock at the first byte, so a client that connects and says nothing (or drips a header a byte at a time)
    kept its slot forever: `max_connections` such clients and every other client got 503."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class HeadTimeoutH11(H11Protocol):
        def connection_made(self, transport: Any) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self.loop.call_later(seconds, self._head_overdue, None)

        def on_response_complete(self) -> None:
            done = self.cycle  # before super(), which may start a pipelined request's cycle
            super().on_response_complete()
            if not self.transport.is_closing():
                self.loop.call_later(seconds, self._head_overdue, done)

        def _head_overdue(self, cycle: Any) -> None:
            # no request head since the timer was armed (a head that arrived made a new cycle): close, as
            # uvicorn's own keep-alive timeout does
            if self.cycle is cycle and not self.transport.is_closing():
                self.transport.close()

    return HeadTimeoutH11


def serve(app: Any, sock: socket.socket, log_level: str, max_connections: int, head_timeout_s: float) -> None:
    """Run until SIGINT/SIGTERM: uvicorn finishes the requests in flight, then returns (exit code 0). A request's
    head must arrive within `head_timeout_s` of its connection (or its previous response)."""
    import uvicorn

    config = uvicorn.Config(
        app,
        log_level=log_level,
        lifespan="on",
        # uvicorn counts the connection asking among its open ones (503 once len(connections) >= limit): with
        # limit_concurrency=max_connections only max_connections - 1 were ever served, and --max-connections 1 none
        limit_concurrency=max_connections + 1,
        http=head_timeout_protocol(head_timeout_s),
    )
    server = uvicorn.Server(config)
    # uvicorn re-raises the signal after its graceful stop: handled here, so a graceful stop exits 0
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: None)
    server.run(sockets=[sock])
    print("stopped: requests in flight finished", flush=True)
