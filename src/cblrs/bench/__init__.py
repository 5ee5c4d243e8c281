"""Benchmarks: the paper's Table I, reference rendering, claims, tracker and pipeline timing.

Every benchmark returns a JSON-ready dict with a ``machine`` entry and medians over repeats;
:mod:`cblrs.bench.report` turns them into markdown tables.
"""

from cblrs.bench.claims import benchmark_claims
from cblrs.bench.lookup import benchmark_lookup
from cblrs.bench.machine import machine_info
from cblrs.bench.render import benchmark_render

__all__ = ["benchmark_claims", "benchmark_lookup", "benchmark_render", "machine_info"]

# benchmark_tracker (cblrs.bench.tracker) and benchmark_pipeline (cblrs.bench.pipeline) import
# the matcher and the evaluation; import them from their modules.
