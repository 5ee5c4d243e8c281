"""Tell a matcher where each of its cameras sees the ground (multi-view confirmation).

The fusion tracker confirms a new, still track only when every camera that sees its place
has seen it (:mod:`cblrs.matching.fusion.coverage`). `cblrs track` tells it each camera's
ground from the reference images it renders; `cblrs matcher` does the same from the
references it is given (``--references DIR``) or renders them from the site file
(``--site``), so that a live matcher tracks as the offline pipeline does.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)


def tell_views(matcher: Any, names: list[str], references: Path | None = None,
               site: Any = None, loaded: dict[Path, Any] | None = None) -> int:
    """Give ``matcher`` (if it takes views) its cameras' ground; the number of cameras told.

    Args:
        matcher: a matcher; one without ``set_views`` is left alone.
        names: the matcher's cameras.
        references: folder of ``<camera>.png`` reference images (read first), or
        site: a :class:`cblrs.site.Site` whose cameras' references are rendered.
        loaded: reference images already read, by path: not read again, and let go once
            the views are set (emptied; 12 MB a camera, the tracker keeps sampled colours).
    """
    set_views = getattr(matcher, "set_views", None)
    if set_views is None:
        if loaded:
            loaded.clear()
        return 0
    # lazy: the PNG reader and the renderer are only needed by a fusion matcher
    from cblrs.reference import ReferenceImage

    started = time.perf_counter()
    images = []
    for name in names:
        path = None if references is None else references / f"{name}.png"
        if path is not None and loaded and path in loaded:
            images.append(loaded[path])
        elif path is not None and path.is_file():
            images.append(ReferenceImage.load(path))
        elif site is not None and name in site.camera_names:
            images.append(site.render_reference(name))
    set_views(images)
    if loaded:
        loaded.clear()
    logger.info("the tracker knows where %d of %d cameras see the ground (%.1f s)",
                len(images), len(names), time.perf_counter() - started)
    return len(images)
