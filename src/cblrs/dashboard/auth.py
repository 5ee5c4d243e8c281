"""Who is asking, and may they: the dashboard's logins, sessions, roles and cross-site guard.

Every route but ``/login``, ``/healthz`` and the static files needs an identity
(:meth:`Authenticator.identify`):

* a **session**: ``POST /api/login`` with a user's name and password from the users file
  (:mod:`cblrs.dashboard.users`), or with the run's login link token, opens one. It has two
  secrets, and every API request of a browser must carry both:

  - its id, in a cookie that scripts cannot read (``HttpOnly``), that no other site's page
    sends (``SameSite=Strict``) and, over TLS, that is never sent in clear (``Secure``,
    ``__Host-`` name);
  - its **page token**, in the ``X-CBLRS-Session`` header (:data:`SESSION_HEADER`). Only the
    login's answer holds it; the page keeps it in ``sessionStorage``, which belongs to the
    page's origin (scheme, host *and port*).

  The cookie alone is worth nothing: browsers send a host's cookies to every port of that
  host, so a server on another port that the user visits receives it; it cannot have the
  page token (no answer hands it out again, and another port's page cannot read the
  dashboard's storage). The page routes themselves (``/``, ``/calibrate``) never look the
  session up (:func:`page`): a request that carries a session cookie or a bearer token, valid
  or not, gets the page's static shell, one without either the redirect to the login page;
  so a caught cookie learns nothing there (not whether it is alive, whose, which role, which
  planes) and keeps nothing alive. A session ends at logout, after
  :attr:`Authenticator.session_s` (absolute) or :attr:`~Authenticator.idle_s` without a
  request, and as soon as its user's role, password or tokens change in the users file;
* an **API token** (``Authorization: Bearer <token>``): a user's token from the users file,
  or, when the dashboard runs without a users file (loopback only), the token of this run
  that ``cblrs dashboard`` prints in its login link.

Roles (:class:`~cblrs.dashboard.users.Role`): a route is guarded by :func:`requires`, the one
decorator every endpoint uses (``@requires(Role.ADMIN)``); it answers 401 to nobody
(a page: a redirect to the login page) and 403 to a role too low.

Cross-site requests: a state-changing request (any method but GET/HEAD/OPTIONS) made with a
session must come from the dashboard's own origin (``Origin``, else ``Referer``); the page
token does the work of a CSRF token as well (another site's page can neither know it nor
send a custom header without a CORS permission that is never given);
:class:`SecurityMiddleware` refuses any such request whose body is
not JSON (415: forms and ``text/plain`` are what a foreign page can send without asking),
and adds the headers that keep the page to itself (a strict Content-Security-Policy with no
inline script, ``frame-ancestors 'none'``, ``nosniff``, ``Referrer-Policy``). Bound to a
loopback address it also refuses requests for any other host name (DNS rebinding).

Failed logins are slowed down (:class:`~cblrs.dashboard.logins.LoginLimiter`): after a few
failures for a user name or from one client, each further attempt waits twice as long as the
previous one, up to five minutes (429 with ``Retry-After``); a browser's login of a user it
has logged in as before (its device cookie, :meth:`Authenticator.device_of`) meets only its
own device's back-off, so failures of others on the same address (every local client is
127.0.0.1) cannot keep a user out of a browser they use; logins wait their turn
(:class:`~cblrs.dashboard.logins.LoginSlots`). Sessions are bounded per user and in all
(:mod:`cblrs.dashboard.sessions`).
"""

from __future__ import annotations

import functools
import hmac
import ipaddress
import logging
import secrets
import time
from collections.abc import Awaitable, Callable, MutableMapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

# optional extra: pip install cblrs[dashboard] (this module serves the dashboard only)
from starlette.requests import Request
from starlette.responses import JSONResponse, RedirectResponse, Response

from cblrs.dashboard.logins import DEVICE_DAYS, LoginLimiter, LoginRefused, device_cookie, device_of
from cblrs.dashboard.sessions import SessionsFull, SessionTable
from cblrs.dashboard.users import Role, User, UsersError, UsersFile, verify_password

logger = logging.getLogger(__name__)

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SESSION_HEADER = "x-cblrs-session"
"""The header that carries a browser session's page token on every API request."""
MAX_BODY_BYTES = 1 << 20
MAX_SESSIONS = 10_000
"""Sessions in all: past it a viewer's login is refused (503), no other session ends."""
SESSIONS_PER_USER = 32
"""Sessions of one user: their next login ends their own session idle the longest."""

CONTENT_SECURITY_POLICY = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob:; "
    "connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'"
)
SECURITY_HEADERS = (
    (b"content-security-policy", CONTENT_SECURITY_POLICY.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"same-origin"),
    (b"x-frame-options", b"DENY"),
    (b"cross-origin-opener-policy", b"same-origin"),
    (b"cross-origin-resource-policy", b"same-origin"),
)

Endpoint = Callable[[Request], Awaitable[Response]]


@dataclass
class Identity:
    """Who a request comes from.

    Attributes:
        user: the user's name.
        role: what they may do.
        via: ``"session"`` (a browser's cookie and page token) or ``"token"`` (an API token).
        stamp: the user's record when the identity was made (:attr:`User.stamp`).
        session: the session id, the cookie's value (sessions only).
        page_token: the session's page token, the ``X-CBLRS-Session`` header's value
            (sessions only; handed out once, in the login's answer).
        created: when the session was opened (monotonic seconds).
        last_seen: the session's last request (monotonic seconds).
    """

    user: str
    role: Role
    via: str
    stamp: str
    session: str | None = None
    page_token: str | None = None
    created: float = 0.0
    last_seen: float = 0.0


class Authenticator:
    """The dashboard's users, sessions and API tokens (see the module docstring).

    Args:
        users_path: the users file (None: no users; then ``run_token`` is the only login).
        run_token: an admin token valid for this run (the login link), or None.
        session_s: a session's lifetime from login.
        idle_s: a session ends after this long without a request (open streams count).
        secure: the dashboard is served over TLS (cookies get ``Secure``).
        origin: the one origin pages are served from (e.g. behind a TLS proxy:
            ``https://dashboard.example.org``); None: the request's own scheme and host.
        loopback: bound to a loopback address: requests must name a loopback host.
        limiter: the login back-off (default: :class:`LoginLimiter` on ``clock``).
        max_sessions: sessions in all (default :data:`MAX_SESSIONS`).
        sessions_per_user: sessions of one user (default :data:`SESSIONS_PER_USER`).
    """

    def __init__(
        self,
        users_path: Path | None = None,
        run_token: str | None = None,
        session_s: float = 12 * 3600.0,
        idle_s: float = 2 * 3600.0,
        secure: bool = False,
        origin: str | None = None,
        loopback: bool = True,
        clock: Callable[[], float] = time.monotonic,
        limiter: LoginLimiter | None = None,
        max_sessions: int | None = None,
        sessions_per_user: int | None = None,
    ):
        if users_path is None and run_token is None:
            raise ValueError("the dashboard needs a users file or a run token")
        self.users_path = users_path
        self.run_token = run_token
        self.session_s, self.idle_s = float(session_s), float(idle_s)
        self.secure = secure or (origin or "").startswith("https://")
        self.origin = origin.rstrip("/") if origin else None
        self.loopback = loopback
        self.clock = clock
        self.limiter = limiter if limiter is not None else LoginLimiter(clock=clock)
        self.cookie_name = "__Host-cblrs_session" if self.secure else "cblrs_session"
        self.device_cookie_name = "__Host-cblrs_device" if self.secure else "cblrs_device"
        self._sessions = SessionTable(
            MAX_SESSIONS if max_sessions is None else max_sessions,
            SESSIONS_PER_USER if sessions_per_user is None else sessions_per_user,
            lambda identity: self._expired(identity, self.clock()))
        self._users: UsersFile | None = None
        self._users_key: tuple[int, int] | None = None
        if users_path is not None:
            self.users()  # a broken file says so at start

    # ------------------------------------------------------------------ users
    def users(self) -> UsersFile | None:
        """The users file as it is now (re-read when it changed on disk).

        Raises:
            UsersError: it cannot be read (at start; later the old one fails closed).
        """
        if self.users_path is None:
            return None
        try:
            status = self.users_path.stat()
            key = (status.st_mtime_ns, status.st_size)
        except OSError:
            key = None
        if key != self._users_key or self._users is None:
            try:
                users = UsersFile.load(self.users_path)
            except UsersError:
                if self._users is None:
                    raise
                logger.error("dashboard: the users file %s cannot be read: nobody is let in "
                             "until it is fixed", self.users_path)
                self._users = UsersFile(self.users_path)
                self._users_key = key
                return self._users
            self._users, self._users_key = users, key
        return self._users

    def _user(self, name: str) -> User | None:
        users = self.users()
        return users.users.get(name) if users is not None else None

    # ------------------------------------------------------------------ identify
    def identify(self, request: Request) -> Identity | None:
        """The request's identity, or None: a bearer token, or a session's cookie together
        with its page token (``X-CBLRS-Session``); a cookie alone is nobody."""
        header = request.headers.get("authorization", "")
        if header[:7].lower() == "bearer ":
            return self._from_token(header[7:].strip())
        identity = self._from_cookie(request)
        if identity is None:
            return None
        given = request.headers.get(SESSION_HEADER, "")
        if not given or not hmac.compare_digest(given.encode(),
                                                (identity.page_token or "").encode()):
            return None
        # Only now is it the session's activity: a cookie without its page token (a server
        # on another port replaying it) must not keep an idle session alive.
        identity.last_seen = self.clock()
        return identity

    def carries_credentials(self, request: Request) -> bool:
        """Whether the request carries a session cookie or a bearer token, valid or not
        (never looked up: for the page routes, :func:`page`)."""
        header = request.headers.get("authorization", "")
        return bool(request.cookies.get(self.cookie_name)) or header[:7].lower() == "bearer "

    def _from_cookie(self, request: Request) -> Identity | None:
        session_id = request.cookies.get(self.cookie_name)
        if not session_id:
            return None
        identity = self._sessions.get(session_id)
        if identity is None or not self.still_valid(identity):
            return None
        return identity

    def _from_token(self, token: str) -> Identity | None:
        if not token:
            return None
        if self.run_token is not None and hmac.compare_digest(token.encode(),
                                                              self.run_token.encode()):
            return Identity("admin", Role.ADMIN, "token", "run")
        users = self.users()
        user = users.find_token(token) if users is not None else None
        if user is None:
            return None
        return Identity(user.name, user.role, "token", user.stamp)

    def still_valid(self, identity: Identity) -> bool:
        """Whether the identity may still act: its session is open and not expired, and its
        user's record is unchanged."""
        if identity.via == "session" and not self._sessions.drop_if(identity):
            return False
        if identity.stamp == "run":
            return self.run_token is not None
        user = self._user(identity.user)
        if user is None or user.stamp != identity.stamp:
            if identity.session is not None:
                self._sessions.drop(identity.session)
            return False
        return True

    # ------------------------------------------------------------------ sessions
    def device_of(self, name: str, request: Request) -> str | None:
        """The known device of user ``name`` that the request's device cookie names, or None
        (no cookie, another user's, a forged one, or one from before a new password)."""
        cookie = request.cookies.get(self.device_cookie_name, "")
        user = self._user(name) if cookie else None
        return device_of(cookie, name, user.password) if user is not None else None

    def set_device_cookie(self, response: Response, name: str, device: str | None) -> None:
        """Give the browser the device cookie of user ``name`` (``device``: keep its known
        device; None: a new one) after a login with their password."""
        user = self._user(name)
        if user is None or not user.password:
            return
        response.set_cookie(self.device_cookie_name, device_cookie(name, user.password, device),
                            max_age=DEVICE_DAYS * 86400, path="/", secure=self.secure,
                            httponly=True, samesite="strict")

    def login(self, name: str, password: str, client: str,
              device: str | None = None) -> Identity:
        """Check ``name`` and ``password`` (slow: scrypt) and open a session; ``device``: the
        user's known device the request comes from (:meth:`device_of`), whose own back-off
        then applies instead of the name's and the address's.

        Raises:
            LoginRefused: wrong name or password (401), or too many failures (429).
        """
        self.limiter.check(name, client, device)
        user = self._user(name)
        # An unknown name costs the same scrypt as a known one (no user enumeration).
        ok = verify_password(password, user.password if user is not None else "")
        if user is None or not ok:
            self.limiter.failed(name, client, device)
            logger.warning("dashboard: failed login for %r from %s%s", name[:64], client,
                           " (a known device)" if device is not None else "")
            if self.users_path is None:
                raise LoginRefused(401, "this dashboard has no users file: open the login "
                                   "link that cblrs dashboard printed.")
            raise LoginRefused(401, "wrong user name or password.")
        self.limiter.succeeded(name, client, device)
        logger.info("dashboard: %s logged in (%s) from %s", name, user.role.label, client)
        return self.open_session(user.name, user.role, user.stamp)

    def open_session(self, user: str, role: Role, stamp: str) -> Identity:
        """Open a session of ``user`` (ending their own idle-longest one at their limit).

        Raises:
            LoginRefused: 503, the dashboard holds its most sessions (an admin's is opened).
        """
        now = self.clock()
        identity = Identity(user, role, "session", stamp, secrets.token_urlsafe(32),
                            secrets.token_urlsafe(32), now, now)
        try:
            ended = self._sessions.add(identity)
        except SessionsFull as full:
            logger.warning("dashboard: refused a session to %s: %d sessions open", user,
                           self._sessions.most)
            raise LoginRefused(503, str(full), 60.0) from None
        if ended:
            logger.info("dashboard: %s holds %d sessions, the most one user may; ended "
                        "their %d idle the longest", user, self._sessions.per_user,
                        len(ended))
        return identity

    def is_run_token(self, token: str) -> bool:
        """Whether ``token`` is this run's login link token."""
        identity = self._from_token(token)
        return identity is not None and identity.stamp == "run"

    def login_with_run_token(self, token: str) -> Identity | None:
        identity = self._from_token(token)
        if identity is None or identity.stamp != "run":
            return None
        return self.open_session(identity.user, identity.role, identity.stamp)

    def logout(self, identity: Identity) -> None:
        self._sessions.drop(identity.session or "")

    def _expired(self, identity: Identity, now: float) -> bool:
        return now - identity.created > self.session_s or now - identity.last_seen > self.idle_s

    def set_cookie(self, response: Response, identity: Identity) -> None:
        assert identity.session is not None
        response.set_cookie(self.cookie_name, identity.session, max_age=int(self.session_s),
                            path="/", secure=self.secure, httponly=True, samesite="strict")

    def clear_cookie(self, response: Response) -> None:
        response.delete_cookie(self.cookie_name, path="/", secure=self.secure, httponly=True,
                               samesite="strict")

    # ------------------------------------------------------------------ cross-site
    def expected_origin(self, request: Request) -> str:
        if self.origin is not None:
            return self.origin
        scheme = "https" if self.secure else "http"
        return f"{scheme}://{request.headers.get('host', '')}"

    def cross_site_problem(self, request: Request) -> str | None:
        """Why a state-changing request may have been made by another site's page, or None.

        ``Origin`` (else ``Referer``) must name the dashboard's origin; a request with a
        session must have one of the two and carry the session's CSRF token.
        """
        expected = self.expected_origin(request)
        origin = request.headers.get("origin")
        referer = request.headers.get("referer")
        if origin is not None:
            if origin != expected:
                return f"a request from {origin[:100]} (another site) is refused."
        elif referer:
            parts = urlsplit(referer)
            if f"{parts.scheme}://{parts.netloc}" != expected:
                return "a request referred by another site is refused."
        return None

    def origin_problem(self, request: Request, identity: Identity) -> str | None:
        """A session's write must say where it comes from (``Origin`` or ``Referer``)."""
        if identity.via != "session":
            return None  # a bearer token is never sent by a browser on its own
        if request.headers.get("origin") is None and not request.headers.get("referer"):
            return "a request without Origin or Referer is refused (reload the page)."
        return None

    def host_problem(self, host_header: str) -> str | None:
        """Bound to loopback: the Host header must name a loopback address (DNS rebinding)."""
        if not self.loopback or self.origin is not None:
            return None
        host = urlsplit(f"//{host_header}").hostname or ""
        if host == "localhost" or host.endswith(".localhost"):
            return None
        try:
            if ipaddress.ip_address(host).is_loopback:
                return None
        except ValueError:
            pass
        return f"host {host_header[:100]!r} is not served here (use 127.0.0.1 or localhost)."


def authenticator(request: Request) -> Authenticator:
    """The application's :class:`Authenticator` (``app.state.auth``)."""
    return request.app.state.auth


def page(endpoint: Endpoint) -> Endpoint:
    """Guard a page route (``/``, ``/calibrate``): static HTML that holds no data.

    A browser's navigation cannot send the page token, so a page request carries the cookie
    alone, which a server on another port of the host receives too. The answer therefore
    depends on the request's path and on whether it carries a session cookie or a bearer
    token at all, never on the session: with either, the page (its script logs in again
    when the session is gone, and the API refuses a role too low); with neither, a redirect
    to the login page. The session is not looked up, so a page request is no activity
    either. The endpoint must not read the session (``request.state.identity`` is unset).
    """

    @functools.wraps(endpoint)
    async def guarded(request: Request) -> Response:
        if not authenticator(request).carries_credentials(request):
            target = request.url.path + (f"?{request.url.query}" if request.url.query else "")
            return RedirectResponse(f"/login?next={quote(target, safe='')}", 303)
        return await endpoint(request)

    return guarded


def requires(role: Role) -> Callable[[Endpoint], Endpoint]:
    """Guard an endpoint: only an identity of ``role`` or higher reaches it.

    Anonymous: 401; a lower role: 403; a state-changing method with a session: also the
    same-origin checks (403). A session needs its page token as well as its cookie
    (:meth:`Authenticator.identify`); pages are guarded by :func:`page` instead. The
    endpoint finds the identity in ``request.state.identity``.

    Example:
        >>> @requires(Role.ADMIN)  # doctest: +SKIP
        ... async def save_place(request): ...
    """

    def decorate(endpoint: Endpoint) -> Endpoint:
        @functools.wraps(endpoint)
        async def guarded(request: Request) -> Response:
            auth = authenticator(request)
            identity = auth.identify(request)
            if identity is None:
                return JSONResponse({"error": "log in first (/login): a browser's session needs "
                                              "its page token (X-CBLRS-Session) as well as "
                                              "its cookie."}, status_code=401,
                                    headers={"WWW-Authenticate": 'Bearer realm="cblrs"'})
            if identity.role < role:
                message = (f"{identity.user} is a {identity.role.label}; this needs an "
                           f"{role.label}." if role == Role.ADMIN else "not allowed.")
                return JSONResponse({"error": message}, status_code=403)
            if request.method not in SAFE_METHODS:
                problem = (auth.cross_site_problem(request)
                           or auth.origin_problem(request, identity))
                if problem is not None:
                    logger.warning("dashboard: refused %s %s for %s: %s", request.method,
                                   request.url.path, identity.user, problem)
                    return JSONResponse({"error": problem}, status_code=403)
            request.state.identity = identity
            return await endpoint(request)

        return guarded

    return decorate


class SecurityMiddleware:
    """ASGI middleware: security headers on every response; every state-changing request
    same-origin, JSON and at most :data:`MAX_BODY_BYTES` (announced or, chunked, counted as it
    arrives); loopback host names only when
    bound to loopback (see the module docstring)."""

    def __init__(self, app: Any, auth: Authenticator):
        self.app = app
        self.auth = auth

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request = Request(scope)
        problem = self.auth.host_problem(request.headers.get("host", ""))
        status = 421
        if problem is None and request.method not in SAFE_METHODS:
            status = 403
            problem = self.auth.cross_site_problem(request)
            if problem is None:
                kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
                if kind != "application/json":
                    status = 415
                    problem = (f"a {request.method} here takes application/json, not "
                               f"{kind or 'no content type'}.")
            if problem is None:
                length = request.headers.get("content-length")
                if length is not None and (not length.isdigit()
                                           or int(length) > MAX_BODY_BYTES):
                    status, problem = 413, "the request body is too large."
        path = scope.get("path", "")
        no_store = not path.startswith("/static/")

        async def send_with_headers(message: MutableMapping[str, Any]) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                headers += SECURITY_HEADERS
                if no_store and not any(name.lower() == b"cache-control" for name, _ in headers):
                    headers.append((b"cache-control", b"no-store"))
                message = {**message, "headers": headers}
            await send(message)

        if problem is not None:
            logger.warning("dashboard: refused %s %s: %s", request.method, path, problem)
            response = JSONResponse({"error": problem}, status_code=status)
            await response(scope, receive, send_with_headers)
            return
        if request.method in SAFE_METHODS:
            await self.app(scope, receive, send_with_headers)
            return
        # A chunked body has no Content-Length: count what arrives, stop at the limit.
        received = 0
        started = False

        async def limited_receive() -> MutableMapping[str, Any]:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > MAX_BODY_BYTES:
                    raise _BodyTooLarge
            return message

        async def send_started(message: MutableMapping[str, Any]) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send_with_headers(message)

        try:
            await self.app(scope, limited_receive, send_started)
        except _BodyTooLarge:
            logger.warning("dashboard: refused %s %s: the request body is too large (over "
                           "%d bytes, chunked)", request.method, path, MAX_BODY_BYTES)
            if not started:
                response = JSONResponse({"error": "the request body is too large."},
                                        status_code=413, headers={"Connection": "close"})
                await response(scope, receive, send_with_headers)


class _BodyTooLarge(Exception):
    """A request body grew past :data:`MAX_BODY_BYTES` while it was read."""
