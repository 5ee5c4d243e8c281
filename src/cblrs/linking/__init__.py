"""Identities across planes: one global id for a person or vehicle that walks or drives from
one plane's matcher into another's.

:mod:`cblrs.linking.links` holds the geometry (overlap bands and portals, the site file's
``links``).
"""

from cblrs.linking.links import LinkError, PlaneLink, build_links

__all__ = ["LinkError", "PlaneLink", "build_links"]
