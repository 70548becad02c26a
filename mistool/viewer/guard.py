"""Who may talk to the viewer: its own page only, as a Jupyter server does.

Every HTTP request and websocket upgrade reaching a viewer's port is checked before viser
sees it:

- **Host**: the ``Host`` header must name the bound address, a loopback name
  (``localhost``, ``127.0.0.1``, ``[::1]``), or a host given with ``--allow-origin``; when
  bound to every interface (``0.0.0.0`` / ``::``) any IP address literal and this
  machine's own names are accepted too. A page served from another name that resolves to
  this machine (DNS rebinding) is refused: 403.
- **Origin** (websocket upgrades): a browser always sends it; it must be the page's own
  origin (``http://<the Host header>``) or one given with ``--allow-origin``. ``null``
  (sandboxed frames, ``file://`` pages) and any other site are refused: 403. A client
  that sends no ``Origin`` is not a browser page and cannot be driven by one: allowed.
- **Token** (beyond loopback): a server bound to a non-loopback address requires a
  per-run random token, given once in the printed URL (``?token=...``); the page's
  response sets an HttpOnly, SameSite=Strict cookie so its own asset and websocket
  requests carry it. A non-browser client may send ``Authorization: token <token>``.
  Without it: 403.

How it hooks into viser 1.1.1, which has no hook for this: its ``WebsockServer`` starts
``websockets.asyncio.server.serve(..., process_request=<its HTTP file server>)`` in a
background thread, and the ``ViserServer`` constructor returns only once the port is
bound. :func:`guarded` replaces that module attribute *for the duration of the
constructor* (a lock serialises constructions) with a wrapper that puts
:meth:`AccessPolicy.refusal` in front of viser's own ``process_request`` -- the documented
``websockets`` hook for exactly this. Nothing of viser is copied or changed, and the
server is stopped and an error raised if the hook was not used (a viser that changed),
so the guard fails closed.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import http
import ipaddress
import secrets
import socket
import threading
import weakref
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar
from urllib.parse import parse_qs, urlsplit

#: Host names that always mean this machine.
LOOPBACK_NAMES: frozenset[str] = frozenset({"localhost", "localhost.localdomain", "ip6-localhost"})
#: Addresses a server may bind without a token (only this machine can connect).
_WILDCARD = frozenset({"0.0.0.0", "::", ""})
#: Bytes of randomness in a per-run token (hex: twice as many characters).
TOKEN_BYTES = 24

T = TypeVar("T")


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a bind address or a host name) only reaches this machine."""
    name = host.strip("[]").lower()
    if name in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def _split_host(value: str) -> str:
    """The host name of a ``Host`` header value or URL netloc, lower case, no port."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value[1:]
    if value.count(":") == 1:
        return value.split(":", 1)[0]
    return value  # a bare IPv6 address or a name without port


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class AccessPolicy:
    """What a viewer server accepts (see the module docs)."""

    bound_host: str
    """The address the server listens on (``--host``)."""
    allow_origins: tuple[str, ...] = ()
    """Extra origins (``http://name:port``) or host names allowed (``--allow-origin``)."""
    token: str | None = None
    """The per-run token required in the URL, cookie or header; None: no token needed."""
    local_names: frozenset[str] = field(default_factory=frozenset)
    """This machine's own names, accepted as Host when bound to every interface."""

    @classmethod
    def for_host(
        cls, host: str, allow_origins: Iterable[str] = (), token: str | None = None
    ) -> AccessPolicy:
        """The policy of a server bound to ``host``: a fresh token unless ``host`` is a
        loopback address (an explicit ``token`` is used as given)."""
        if token is None and not is_loopback(host):
            token = secrets.token_hex(TOKEN_BYTES)
        names: set[str] = set()
        if not is_loopback(host):
            with contextlib.suppress(OSError):
                names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        return cls(host, tuple(allow_origins), token, frozenset(names))

    @property
    def cookie_name(self) -> str:
        """The cookie carrying the token (named after it, so two servers on one host
        never overwrite each other's)."""
        digest = hashlib.sha256((self.token or "").encode()).hexdigest()[:12]
        return f"mistool-token-{digest}"

    def host_allowed(self, host_header: str | None) -> bool:
        """Whether a request's ``Host`` header names this server (module docs)."""
        if not host_header:
            return False
        name = _split_host(host_header)
        bound = self.bound_host.strip("[]").lower()
        if is_loopback(name) or name == bound or name in self._allowed_hosts():
            return True
        return bound in _WILDCARD and (_is_ip(name) or name in self.local_names)

    def origin_allowed(self, origin: str | None, host_header: str | None) -> bool:
        """Whether a websocket upgrade's ``Origin`` is the page's own (module docs)."""
        if origin is None:
            return True  # not a browser page
        origin = origin.strip().lower()
        if origin in {o.lower().rstrip("/") for o in self.allow_origins}:
            return True
        parts = urlsplit(origin)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            return False  # "null", file://, anything odd
        if host_header and parts.netloc == host_header.strip().lower():
            return True
        return _split_host(parts.netloc) in self._allowed_hosts()

    def _allowed_hosts(self) -> set[str]:
        hosts = set()
        for item in self.allow_origins:
            netloc = urlsplit(item).netloc if "://" in item else item
            hosts.add(_split_host(netloc))
        return hosts

    def token_given(self, path: str, headers: Mapping[str, str]) -> bool:
        """Whether the request carries the token (query, cookie or Authorization)."""
        if self.token is None:
            return True
        offered = [*parse_qs(urlsplit(path).query).get("token", [])]
        auth = headers.get("Authorization") or ""
        if auth.lower().startswith("token "):
            offered.append(auth[6:].strip())
        for chunk in (headers.get("Cookie") or "").split(";"):
            name, _, value = chunk.strip().partition("=")
            if name == self.cookie_name:
                offered.append(value)
        return any(hmac.compare_digest(t.encode(), self.token.encode()) for t in offered)

    def refusal(self, path: str, headers: Mapping[str, str]) -> tuple[int, str] | None:
        """``(status, reason)`` when the request must be refused, else None."""
        host = headers.get("Host")
        if not self.host_allowed(host):
            return 403, f"Host {host!r} is not this server (mistool serve --allow-origin)"
        upgrade = (headers.get("Upgrade") or "").lower() == "websocket"
        if upgrade and not self.origin_allowed(headers.get("Origin"), host):
            return 403, f"Origin {headers.get('Origin')!r} may not use this viewer"
        if not self.token_given(path, headers):
            return 403, "open the URL with ?token=... that mistool serve printed"
        return None

    def set_cookie(self, path: str) -> str | None:
        """The ``Set-Cookie`` value when ``path`` carries the token in its query."""
        if self.token is None or self.token not in parse_qs(urlsplit(path).query).get("token", []):
            return None
        return f"{self.cookie_name}={self.token}; Path=/; HttpOnly; SameSite=Strict"


def _guard_process_request(
    inner: Callable[..., Any] | None, policy: AccessPolicy
) -> Callable[..., Any]:
    """``process_request`` for ``websockets``: the policy first, then viser's own."""

    def process_request(connection: Any, request: Any) -> Any:
        try:
            refused = policy.refusal(request.path, request.headers)
        except Exception:  # noqa: BLE001 - e.g. two Host headers: refuse, never pass
            refused = (400, "malformed request headers")
        if refused is not None:
            status, reason = refused
            return connection.respond(http.HTTPStatus(status), reason + "\n")
        response = inner(connection, request) if inner is not None else None
        cookie = policy.set_cookie(request.path)
        if response is not None and cookie is not None:
            response.headers["Set-Cookie"] = cookie
        return response

    return process_request


_construct_lock = threading.Lock()
_policies: weakref.WeakKeyDictionary[Any, AccessPolicy] = weakref.WeakKeyDictionary()


def guarded(make_server: Callable[[], T], policy: AccessPolicy) -> T:
    """Construct a viser server with ``make_server()`` so that every request to it
    passes ``policy`` first (module docs). Raises RuntimeError, with the server stopped,
    if viser did not start its server through the hooked function."""
    import websockets.asyncio.server as ws_server

    used = []
    with _construct_lock:
        original = ws_server.serve

        def serve(*args: Any, **kwargs: Any) -> Any:
            kwargs["process_request"] = _guard_process_request(
                kwargs.get("process_request"), policy
            )
            used.append(True)
            return original(*args, **kwargs)

        ws_server.serve = serve  # type: ignore[misc,assignment]  # a class in the stubs
        try:
            server = make_server()
        finally:
            ws_server.serve = original  # type: ignore[misc]
    if not used:
        with contextlib.suppress(Exception):
            server.stop()  # type: ignore[attr-defined]
        raise RuntimeError(
            "mistool's viewer guard was not installed (viser no longer starts its server "
            "through websockets.asyncio.server.serve); refusing to serve unguarded"
        )
    _policies[server] = policy
    return server


def policy_of(server: Any) -> AccessPolicy | None:
    """The policy a server was constructed with by :func:`guarded`."""
    return _policies.get(server)


def with_token(server: Any, url: str) -> str:
    """``url`` with the server's token query (``/?token=...``) when it needs one."""
    policy = policy_of(server)
    if policy is None or policy.token is None:
        return url
    return f"{url.rstrip('/')}/?token={policy.token}"
