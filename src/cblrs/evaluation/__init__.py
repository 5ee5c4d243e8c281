"""Scoring of world tracks: HOTA, DetA, AssA, LocA, MOTA, IDF1 (TrackEval, AI City 2024)."""

from cblrs.evaluation.metrics import Metrics, build_trackeval_data, evaluate, first_rows

__all__ = ["Metrics", "build_trackeval_data", "evaluate", "first_rows"]
