"""Experiments of the paper, rerun on synthetic and WILDTRACK data: targeting, resolution."""
