"""``cblrs up``: a whole site from its site file in one command.

:mod:`cblrs.up.plan` turns a site file (every camera with a ``source:``) into a plan — the
broker's secured configuration, the references, one command line per process;
:mod:`cblrs.up.runner` starts the processes in order, watches them and stops them in order;
:mod:`cblrs.up.units` writes the same processes as systemd units and a container definition.
"""

from cblrs.up.host import find_broker
from cblrs.up.plan import SitePlan, UpError, make_plan, prepare
from cblrs.up.runner import SiteRunner, database_counts
from cblrs.up.units import systemd_units, write_container, write_systemd

__all__ = [
    "SitePlan",
    "SiteRunner",
    "UpError",
    "database_counts",
    "find_broker",
    "make_plan",
    "prepare",
    "systemd_units",
    "write_container",
    "write_systemd",
]
