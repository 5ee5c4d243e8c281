"""Dataset readers and generators; each produces a :class:`cblrs.datasets.scene.Scene`."""

from cblrs.datasets.multiview import load_scene
from cblrs.datasets.scene import Scene

__all__ = ["Scene", "load_scene"]
