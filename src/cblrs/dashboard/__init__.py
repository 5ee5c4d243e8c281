"""The live dashboard: a web page of the site with live tracks, counts, cameras, replay and
calibration (``cblrs dashboard``).

:mod:`cblrs.dashboard.scene` reduces a site to what the page draws, :mod:`~cblrs.dashboard.feed`
relays the plane's MQTT messages (read-only viewer) to pages, :mod:`~cblrs.dashboard.replay`
plays a matcher's stored run, :mod:`~cblrs.dashboard.calibration` serves the calibration
page, and :mod:`~cblrs.dashboard.app` is the Starlette application (the ``dashboard`` extra).
The page itself (``static/``) is plain HTML, CSS and JavaScript: no build, no CDN.
"""
