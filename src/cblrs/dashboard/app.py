"""The dashboard's web application (Starlette; served by uvicorn from ``cblrs dashboard``).

Pages (static files shipped with the package, no build step, nothing fetched from a CDN):

* ``/`` — the overview of a site of several planes (``cblrs dashboard`` without ``--plane``,
  or ``--plane all``): every plane's map placed by the site's geometry, the live tracks of
  every plane with their global ids (from the linker), site-wide counts, each plane's matcher
  health and a link to each plane's own page, ``/?plane=N``;
* ``/`` (one plane), ``/?plane=N`` (a plane of the overview) — the live map: the site's planes,
  zones, counting lines, cameras and their fields of view; live tracks with short trails
  coloured by id (and their global ids); zones and lines with their counts; per-camera status;
  the event log; a replay of a stored run at 1x-10x; a heatmap of recent positions; for admins,
  an editor of the zones and lines (saved to the site file);
* ``/calibrate`` — a camera's frame beside the site map: click point pairs, see each
  point's reprojection error live, save to the site file and render the reference.

API (JSON, and Server-Sent Events for the streams, which the pages read with ``fetch``: an
``EventSource`` cannot send the page token):

* ``GET /api/site``, ``GET /api/site?plane=N|all`` — the site as drawn
  (:func:`cblrs.dashboard.scene.site_scene`);
* ``GET /api/stream``, ``GET /api/stream?plane=N|all`` — the live feed
  (:mod:`cblrs.dashboard.feed`) of the plane shown, of plane N, or of every plane;
* ``GET /api/replay/info``, ``GET /api/replay?speed=S&start=T`` — a stored run
  (:mod:`cblrs.dashboard.replay`);
* ``GET /api/status`` — what the dashboard is connected to;
* ``GET /map`` — the site map image;
* ``GET /api/calibrate/cameras``, ``GET /api/calibrate/frame/{camera}``,
  ``POST /api/calibrate/fit``, ``POST /api/calibrate/save``,
  ``GET /api/calibrate/reference/{camera}`` — the calibration page
  (:mod:`cblrs.dashboard.calibration`);
* ``GET /api/places`` (viewers may read), ``POST /api/places/save`` (admins) — the map's
  places editor (:mod:`cblrs.dashboard.places_editor`);
* ``GET /login``, ``POST /api/login``, ``POST /api/logout``, ``GET /api/session`` — logging
  in (the answer holds the session's page token, which every later request carries in
  ``X-CBLRS-Session`` beside the cookie, and sets the browser's device cookie, whose later
  logins of that user meet only their own back-off) and out, and who the page's user is.

Who may do what (:mod:`cblrs.dashboard.auth`): ``/login``, ``/healthz`` and ``/static``
are open; every other route needs a viewer, and the calibration page and its API, and saving
places, an admin.
Each endpoint states its role with :func:`~cblrs.dashboard.auth.requires`; the pages
(static shells, no data) are guarded by :func:`~cblrs.dashboard.auth.page`, which answers
by the address alone.
"""

from __future__ import annotations

import asyncio
import logging
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cblrs.dashboard import calibration, places_editor
from cblrs.dashboard.feed import LiveFeed, sse
from cblrs.dashboard.replay import ReplayError, StoredRunInfo, StoreReplay
from cblrs.dashboard.scene import map_image, site_scene
from cblrs.dashboard.users import Role
from cblrs.errors import CblrsError
from cblrs.site import Site, load_site

logger = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
KEEPALIVE_S = 15.0
"""A live stream says something this often when the plane is quiet (and checks that its
session is still open)."""
STREAMS_PER_USER = 8
"""Live streams and replays one user may hold open at once, over all their sessions and
tokens (a page holds one): each holds a queue or a database connection, so one viewer could
otherwise take up the dashboard's memory and connections by opening them by the thousand."""


@dataclass
class DashboardConfig:
    """What one dashboard serves.

    Attributes:
        site_path: the site file (read at start; the calibration page and the places editor
            rewrite it).
        plane_id: the plane shown (default: the site's first); None with ``overview``.
        overview: serve the overview of every plane at ``/`` (each plane's page at
            ``/?plane=N``).
        feed: the live feed (None: replay only).
        database: a matcher database to replay (None: no replay).
        frames: folder of camera frames for the calibration page.
        references: where the calibration page writes rendered references.
        broker: the broker's address, for the page's header.
        to_site: the key's pseudo -> site mapping when the matcher works on a pseudo site
            (replayed positions are mapped with it); None otherwise.
    """

    site_path: Path
    plane_id: int | None = None
    overview: bool = False
    feed: LiveFeed | None = None
    database: Path | None = None
    frames: Path | None = None
    references: Path | None = None
    broker: str = ""
    to_site: Any = None
    site: Site = field(init=False)

    def __post_init__(self) -> None:
        self.site = load_site(self.site_path)
        if self.references is None:
            self.references = self.site_path.parent / "references"

    @property
    def planes(self) -> list[int]:
        """The site's plane ids (``[plane_id]`` or ``[1]`` for a site without planes)."""
        if self.site.planes is not None:
            return list(self.site.planes.ids)
        return [self.plane_id if self.plane_id is not None else 1]

    def shown(self, text: str | None) -> int | None:
        """The plane a request asks for (``?plane=N``; ``all``: the overview, None).

        Raises:
            ValueError: not a plane this dashboard shows.
        """
        if self.overview:
            first = None
        else:  # one plane: the configured one, else the site's first
            first = self.plane_id if self.plane_id is not None else self.planes[0]
        if text is None or text == "":
            return first
        if text == "all":
            if not self.overview:
                raise ValueError("this dashboard shows one plane (cblrs dashboard --plane).")
            return None
        if not text.isdecimal() or int(text) not in self.planes:
            raise ValueError(f"plane {text[:20]!r} is not a plane of this site "
                             f"(planes {self.planes}).")
        plane = int(text)
        if not self.overview and plane != first:
            raise ValueError(f"this dashboard shows plane {first} only.")
        return plane


def create_app(config: DashboardConfig, auth: Any) -> Any:
    """The ASGI application (needs the ``dashboard`` extra: Starlette).

    Args:
        config: what it serves.
        auth: who may use it (:class:`cblrs.dashboard.auth.Authenticator`).
    """
    try:
        # optional extra: pip install cblrs[dashboard]
        from starlette.applications import Starlette
        from starlette.middleware import Middleware
        from starlette.responses import (
            FileResponse,
            JSONResponse,
            Response,
            StreamingResponse,
        )
        from starlette.routing import Mount, Route
        from starlette.staticfiles import StaticFiles

        from cblrs.dashboard.auth import (
            LoginRefused,
            SecurityMiddleware,
            page,
            requires,
        )
        from cblrs.dashboard.logins import LoginSlots
    except ImportError:  # pragma: no cover - depends on the environment
        raise CblrsError(
            "the dashboard needs Starlette and uvicorn: pip install cblrs[dashboard]"
        ) from None

    viewer, admin = Role.VIEWER, Role.ADMIN
    scene_cache: dict[str, Any] = {}
    places_lock = asyncio.Lock()  # one save of the site file at a time
    logins = LoginSlots()  # one at a time per name and address, two checked at once
    open_streams: dict[str, int] = {}  # user -> live streams and replays open

    def take_stream(user: str) -> Callable[[], None] | None:
        """Count one more stream of ``user``: the call that releases it, or None (at the
        limit)."""
        if open_streams.get(user, 0) >= STREAMS_PER_USER:
            logger.warning("dashboard: refused a stream to %s: %d open", user,
                           STREAMS_PER_USER)
            return None
        open_streams[user] = open_streams.get(user, 0) + 1
        released = False

        def release() -> None:
            nonlocal released
            if not released:
                released = True
                left = open_streams.pop(user, 1) - 1
                if left > 0:
                    open_streams[user] = left

        return release

    def streaming(body: Any, release: Callable[[], None]) -> Any:
        """The event stream of ``body``, whose end (or a body never started, when the page
        left first) gives its slot back."""
        weakref.finalize(body, release)
        return StreamingResponse(body, media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache"})

    def too_many_streams(user: str) -> Any:
        return JSONResponse({"error": f"{user} has {STREAMS_PER_USER} live streams and "
                                      "replays open, the most one user may; close a page "
                                      "first."}, status_code=429)

    def scene(plane: int | None = -1) -> dict[str, Any]:
        """The scene of ``plane`` (None: every plane; the default: the configured one)."""
        shown = config.plane_id if plane == -1 else plane
        key = "all" if shown is None else str(shown)
        if key not in scene_cache:
            scene_cache[key] = site_scene(config.site, shown, every_plane=shown is None)
        return scene_cache[key]

    def asked_plane(request: Any) -> int | None:
        """The plane the request names (``ValueError``: not one shown here)."""
        return config.shown(request.query_params.get("plane"))

    # -- logging in -----------------------------------------------------------------------

    async def login_page(request: Any) -> Any:
        # The run's login link (?token=...): the page posts the token to /api/login, whose
        # answer alone holds the session's page token; an invalid link is told at once.
        token = request.query_params.get("token")
        if token is not None and not auth.is_run_token(token):
            return FileResponse(STATIC / "login.html", status_code=401)
        return FileResponse(STATIC / "login.html")

    def logged_in(identity: Any) -> Any:
        """The answer to a login: the session's cookie, and its page token (given here only:
        the page keeps it in its origin's sessionStorage and sends it on every request)."""
        response = JSONResponse({"user": identity.user, "role": identity.role.label,
                                 "session": identity.page_token})
        auth.set_cookie(response, identity)
        return response

    async def login(request: Any) -> Any:
        try:
            data = await request.json()
            if isinstance(data, dict) and set(data) == {"token"}:
                identity = auth.login_with_run_token(str(data["token"]))
                if identity is None:
                    return JSONResponse({"error": "this login link is not valid: it changes "
                                                  "each time the dashboard starts."},
                                        status_code=401)
                return logged_in(identity)
            name, password = str(data["user"]), str(data["password"])
        except (ValueError, KeyError, TypeError):
            return JSONResponse({"error": "give user and password."}, status_code=400)
        client = request.client.host if request.client else "?"
        device = auth.device_of(name, request)  # a browser that logged in as name before
        try:
            auth.limiter.check(name, client, device)  # a locked name waits in no queue
            async with logins.slot(name, client if device is None else f"{client} {device}"):
                identity = await asyncio.to_thread(auth.login, name, password, client, device)
        except LoginRefused as refused:
            headers = ({"Retry-After": str(max(1, round(refused.retry_after_s)))}
                       if refused.status in (429, 503) else None)
            return JSONResponse({"error": str(refused)}, status_code=refused.status,
                                headers=headers)
        response = logged_in(identity)
        auth.set_device_cookie(response, name, device)
        return response

    @requires(viewer)
    async def logout(request: Any) -> Any:
        auth.logout(request.state.identity)
        response = JSONResponse({"logged_out": True})
        auth.clear_cookie(response)
        return response

    @requires(viewer)
    async def session(request: Any) -> Any:
        identity = request.state.identity
        return JSONResponse({"user": identity.user, "role": identity.role.label,
                             "via": identity.via})

    # -- the map --------------------------------------------------------------------------

    # The pages answer by their address alone, never by the session or the site (see
    # auth.page): a plane's page, or the overview at ?plane=all; a plane's page that finds
    # the dashboard is an overview goes there, and one of a plane not shown says so.
    @page
    async def index(request: Any) -> Any:
        overview = request.query_params.get("plane") == "all"
        return FileResponse(STATIC / ("overview.html" if overview else "index.html"))

    @page
    async def calibrate_page(request: Any) -> Any:
        return FileResponse(STATIC / "calibrate.html")

    @requires(viewer)
    async def site(request: Any) -> Any:
        try:
            plane = asked_plane(request)
        except ValueError as error:
            return refusal(error, 404)
        data = await asyncio.to_thread(scene, plane)
        return JSONResponse({
            **data, "live": config.feed is not None, "overview": config.overview,
            "site_planes": config.planes,
            "replay": config.database is not None and not config.overview,
            "broker": config.broker})

    @requires(viewer)
    async def site_map(request: Any) -> Any:
        image = map_image(config.site)
        if image is None:
            return Response("the site has no map image\n", status_code=404)
        return Response(image[0], media_type=image[1])

    @requires(viewer)
    async def status(request: Any) -> Any:
        feed = config.feed
        return JSONResponse({
            "live": feed is not None,
            "connected": bool(feed and feed.connected),
            "messages": feed.counters if feed else {},
            "replay": config.database.name if config.database else None,  # not its folder
        })

    @requires(viewer)
    async def stream(request: Any) -> Any:
        feed = config.feed
        if feed is None:
            return JSONResponse({"error": "this dashboard has no broker (--broker)."},
                                status_code=404)
        try:
            plane = asked_plane(request)
        except ValueError as error:
            return refusal(error, 404)
        identity = request.state.identity
        release = take_stream(identity.user)
        if release is None:
            return too_many_streams(identity.user)
        subscriber = feed.subscribe(asyncio.get_running_loop(), plane)

        async def body():
            try:
                while auth.still_valid(identity):
                    try:
                        item = await asyncio.wait_for(subscriber.next(), KEEPALIVE_S)
                    except TimeoutError:
                        yield b": keep-alive\n\n"  # also finds pages that went away
                        continue
                    identity.last_seen = auth.clock()  # an open stream is activity
                    yield sse(item)
            finally:
                feed.unsubscribe(subscriber)
                release()

        return streaming(body(), release)

    def replay_refusal(error: ReplayError, status: int) -> Any:
        """The refusal of a replay, naming the database by its file name (viewers read it;
        the server's folders are not theirs to know)."""
        text = str(error)
        if config.database is not None:
            text = text.replace(str(config.database), config.database.name)
        return JSONResponse({"error": text}, status_code=status)

    def open_replay() -> StoreReplay:
        if config.database is None:
            raise ReplayError("this dashboard has no stored run (--db).")
        return StoreReplay(config.database, config.to_site)

    stored_run = StoredRunInfo(open_replay)  # read in a thread, at most every 10 s

    @requires(viewer)
    async def replay_info(request: Any) -> Any:
        try:
            return JSONResponse(await stored_run.get())
        except ReplayError as error:
            return replay_refusal(error, 404)

    @requires(viewer)
    async def replay(request: Any) -> Any:
        try:
            speed = float(request.query_params.get("speed", "1"))
            start_text = request.query_params.get("start")
            start = float(start_text) if start_text else None
        except ValueError:
            return JSONResponse({"error": "speed and start must be numbers."}, status_code=400)
        identity = request.state.identity
        release = take_stream(identity.user)
        if release is None:
            return too_many_streams(identity.user)
        try:
            info = await stored_run.get()
            stored = await asyncio.to_thread(open_replay)
        except ReplayError as error:
            release()
            return replay_refusal(error, 404)
        messages = stored.messages(speed, start, info)
        try:
            first = await messages.__anext__()  # errors (speed, empty run) as an answer
        except ReplayError as error:
            stored.close()
            release()
            return replay_refusal(error, 400)

        async def body():
            try:
                yield sse(first)
                async for item in messages:
                    if not auth.still_valid(identity):
                        break
                    identity.last_seen = auth.clock()
                    yield sse(item)
            finally:
                stored.close()
                release()

        return streaming(body(), release)

    # -- calibration (admins) -------------------------------------------------------------

    def refusal(error: Exception, status_code: int = 422) -> Any:
        return JSONResponse({"error": str(error)}, status_code=status_code)

    @requires(admin)
    async def calibrate_cameras(request: Any) -> Any:
        cameras = await asyncio.to_thread(calibration.camera_list, config.site, config.frames)
        return JSONResponse({"cameras": cameras, "map": scene()["map"],
                             "bounds": scene()["bounds"], "site": config.site.source})

    @requires(admin)
    async def calibrate_frame(request: Any) -> Any:
        camera = request.path_params["camera"]
        try:
            path = calibration.frame_path(config.site, camera, config.frames)
        except CblrsError as error:
            return refusal(error, 404)
        if path is None:
            return refusal(CblrsError(f"no frame for camera {camera}; open one from a file."),
                           404)
        return FileResponse(path)

    @requires(admin)
    async def calibrate_fit(request: Any) -> Any:
        try:
            data = await request.json()
            result = await asyncio.to_thread(
                calibration.fit_points, config.site, str(data.get("camera")),
                data.get("points"), data.get("image_size"), str(data.get("model", "auto")),
                _optional_float(data.get("focal_px")), str(data.get("unit", "metres")),
                data.get("left_handed") is True,
            )
        except (CblrsError, ValueError, AttributeError) as error:
            return refusal(error)
        return JSONResponse(result)

    @requires(admin)
    async def calibrate_save(request: Any) -> Any:
        assert config.references is not None
        try:
            data = await request.json()
            result = await asyncio.to_thread(
                calibration.save_points, config.site_path, str(data.get("camera")),
                data.get("points"), data.get("image_size"), config.references,
                str(data.get("model", "auto")), _optional_float(data.get("focal_px")),
                str(data.get("unit", "metres")), data.get("left_handed") is True,
            )
        except (CblrsError, ValueError, AttributeError) as error:
            return refusal(error)
        logger.info("dashboard: %s saved the calibration of %s", request.state.identity.user,
                    data.get("camera"))
        config.site = load_site(config.site_path)
        scene_cache.clear()
        return JSONResponse(result)

    @requires(admin)
    async def calibrate_reference(request: Any) -> Any:
        assert config.references is not None
        try:
            png = await asyncio.to_thread(
                calibration.reference_preview, config.site, request.path_params["camera"],
                config.references, config.frames)
        except CblrsError as error:
            return refusal(error, 404)
        return Response(png, media_type="image/png")

    # -- places drawn on the map (admins save) ------------------------------------------

    @requires(viewer)
    async def places(request: Any) -> Any:
        try:
            plane = asked_plane(request)
        except ValueError as error:
            return refusal(error, 404)
        if plane is None:
            return refusal(CblrsError("places are edited on a plane's page (?plane=N)."), 404)
        view = await asyncio.to_thread(places_editor.places_view, config.site,
                                       config.site_path, plane)
        return JSONResponse(view)

    @requires(admin)
    async def places_save(request: Any) -> Any:
        try:
            data = await request.json()
            plane = asked_plane(request)
        except ValueError:
            return refusal(CblrsError("send the places as JSON, to a plane shown here."), 400)
        if plane is None:
            return refusal(CblrsError("places are saved from a plane's page (?plane=N)."), 400)
        async with places_lock:
            try:
                result = await asyncio.to_thread(places_editor.save_places, config.site_path,
                                                 data, plane)
            except CblrsError as error:
                return refusal(error)
            config.site = load_site(config.site_path)
            scene_cache.clear()
        logger.info("dashboard: %s saved %d zones and %d lines to %s",
                    request.state.identity.user, result["zones"], result["lines"],
                    config.site_path)
        return JSONResponse(result)

    async def healthz(request: Any) -> Any:
        return Response("ok\n", media_type="text/plain")

    async def favicon(request: Any) -> Any:
        return Response(status_code=204)

    routes = [
        Route("/", index),
        Route("/login", login_page),
        Route("/calibrate", calibrate_page),
        Route("/healthz", healthz),
        Route("/favicon.ico", favicon),
        Route("/map", site_map),
        Route("/api/login", login, methods=["POST"]),
        Route("/api/logout", logout, methods=["POST"]),
        Route("/api/session", session),
        Route("/api/site", site),
        Route("/api/status", status),
        Route("/api/stream", stream),
        Route("/api/replay/info", replay_info),
        Route("/api/replay", replay),
        Route("/api/places", places),
        Route("/api/places/save", places_save, methods=["POST"]),
        Route("/api/calibrate/cameras", calibrate_cameras),
        Route("/api/calibrate/frame/{camera}", calibrate_frame),
        Route("/api/calibrate/fit", calibrate_fit, methods=["POST"]),
        Route("/api/calibrate/save", calibrate_save, methods=["POST"]),
        Route("/api/calibrate/reference/{camera}", calibrate_reference),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    app = Starlette(routes=routes, middleware=[Middleware(SecurityMiddleware, auth=auth)])
    app.state.auth = auth
    return app


def server_config(app: Any, tls_cert: Path | None = None, tls_key: Path | None = None,
                  **limits: Any) -> Any:
    """uvicorn's configuration for the dashboard's application ``app``.

    Connections are limited as :func:`~cblrs.dashboard.connections.guarded_protocol` says
    (``limits`` are its arguments): a client that never finishes a request's headers, or
    holds many connections, cannot take the dashboard from everyone else.

    ``X-Forwarded-For`` and ``X-Forwarded-Proto`` are ignored (uvicorn trusts them from
    127.0.0.1 by default): the login back-off and the log count the address of the
    connection, which a client on the same machine cannot choose (behind a proxy: the
    proxy's).
    """
    import uvicorn  # optional extra: pip install cblrs[dashboard]

    from cblrs.dashboard.connections import guarded_protocol

    return uvicorn.Config(
        app, http=guarded_protocol(**limits), log_level="warning", access_log=False,
        lifespan="off", proxy_headers=False,
        server_header=False,
        ssl_certfile=str(tls_cert) if tls_cert else None,
        ssl_keyfile=str(tls_key) if tls_key else None,
    )


def _optional_float(value: Any) -> float | None:
    if value is None or value == "":
        return None
    return float(value)
