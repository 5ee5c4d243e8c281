"""One description of a site: planes, cameras, site map and places (``site.yaml``).

The schema and its error messages are in :mod:`cblrs.site.schema`, a loaded :class:`Site`
in :mod:`cblrs.site.core`, camera geometry (files, inline, homography, clicked points) in
:mod:`cblrs.site.cameras`, ``cblrs site init`` in :mod:`cblrs.site.dataset` and ``cblrs site
check`` in :mod:`cblrs.site.check`.

Example:
    >>> site = parse_site('''
    ... version: 1
    ... planes: [{id: 1, origin: [0, 0], size: [20, 10]}]
    ... cameras:
    ...   - {name: gate, image_size: [1280, 720],
    ...      homography: [[-27.66, 11.3, 654.0], [1.25, 0.87, 64.5], [-0.0207, -0.0145, 1]]}
    ... ''')
    >>> site.camera_names, site.camera("gate").camera.has_pose
    (['gate'], False)
"""

from cblrs.site.check import check_site, format_check
from cblrs.site.core import (
    Site,
    SiteCamera,
    SiteMap,
    backup_document,
    load_site,
    parse_site,
    save_document,
)
from cblrs.site.dataset import site_from_dataset
from cblrs.site.schema import SITE_VERSION, SiteError, SiteModel, dump_document

__all__ = [
    "SITE_VERSION",
    "Site",
    "SiteCamera",
    "SiteError",
    "SiteMap",
    "SiteModel",
    "backup_document",
    "check_site",
    "dump_document",
    "format_check",
    "load_site",
    "parse_site",
    "save_document",
    "site_from_dataset",
]
