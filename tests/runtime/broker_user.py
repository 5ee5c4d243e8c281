"""Which user test brokers run as (imported by the runtime tests and their fixtures)."""

from __future__ import annotations

import os

RUN_AS = "root" if os.geteuid() == 0 else None
"""Test brokers keep their files in pytest's private temporary folders, which the
``mosquitto`` service user cannot enter: as root they run as root (never in production)."""
