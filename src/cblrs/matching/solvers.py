"""SciPy's assignment and non-negative least-squares solvers, without importing ``scipy.optimize``.

The trackers call two compiled SciPy routines: the rectangular assignment solver behind
:func:`scipy.optimize.linear_sum_assignment` and the Lawson-Hanson solver behind
:func:`scipy.optimize.nnls`. Importing ``scipy.optimize`` to reach them loads most of SciPy
(linalg, special, fft, sparse, spatial, stats' distributions): a third of a second of CPU
for every ``cblrs track`` process, more than loading WILDTRACK and rendering its colours.
The two routines live in their own extension modules (``scipy.optimize._lsap`` and
``scipy.optimize._slsqplib``), which need only numpy; this module loads those two
without running ``scipy.optimize``'s package initialisation (nor ``scipy``'s), registered
under their own names (a later ``import scipy.optimize`` uses the very same modules). Same
compiled code, same results, bit for bit (tested against the public functions).

Should a SciPy release move them, the public functions are imported instead: slower to
start, same answers.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import logging
import os
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

logger = logging.getLogger(__name__)


def _extension(package: str, name: str) -> ModuleType | None:
    """The extension module ``package.name`` loaded without running ``package``'s
    ``__init__``; None when it cannot be found or loaded."""
    full = f"{package}.{name}"
    if full in sys.modules:
        return sys.modules[full]
    try:
        # The top package's folder, found without importing it (scipy's __init__ alone is
        # 20 ms of start-up: its test utilities, subprocess, version parsing).
        top, *inner = package.split(".")
        found = importlib.util.find_spec(top)
        if found is None or found.submodule_search_locations is None:
            return None
        folders = [os.path.join(folder, *inner) for folder in found.submodule_search_locations]
        spec = importlib.machinery.PathFinder.find_spec(full, folders)
        if spec is None or not isinstance(spec.loader, importlib.machinery.ExtensionFileLoader):
            return None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except (ImportError, OSError) as error:
        logger.debug("could not load %s on its own (%s); using scipy.optimize", full, error)
        return None
    sys.modules[full] = module
    return module


def _solvers() -> tuple[Callable[..., Any], Callable[..., Any] | None]:
    """``(linear_sum_assignment, raw nnls or None)``."""
    assignment = _extension("scipy.optimize", "_lsap")
    least_squares = _extension("scipy.optimize", "_slsqplib")
    raw_nnls = getattr(least_squares, "nnls", None)
    function = getattr(assignment, "linear_sum_assignment", None)
    if function is None:
        from scipy.optimize import linear_sum_assignment as function
    return function, raw_nnls


_linear_sum_assignment, _raw_nnls = _solvers()


def linear_sum_assignment(cost: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """:func:`scipy.optimize.linear_sum_assignment` (minimise): ``(rows, columns)``.

    Args:
        cost: (R, C) float cost matrix.
    """
    return _linear_sum_assignment(cost)


def nnls(matrix: ArrayLike, target: ArrayLike) -> tuple[NDArray[np.float64], float]:
    """:func:`scipy.optimize.nnls` with its default iteration limit: ``argmin ||A x - b||``
    over ``x >= 0``, and the residual norm.

    Args:
        matrix: (M, N) float A.
        target: (M,) float b.

    Raises:
        ValueError: A or b holds a non-finite value, or their shapes do not fit.
        RuntimeError: the iteration limit (3 N) was reached.
    """
    if _raw_nnls is None:
        from scipy.optimize import nnls as public

        return public(matrix, target)
    # The checks of scipy.optimize.nnls, then its compiled routine with its default limit.
    matrix = np.asarray_chkfinite(matrix, dtype=np.float64, order="C")
    target = np.asarray_chkfinite(target, dtype=np.float64)
    if matrix.ndim != 2 or target.ndim != 1 or matrix.shape[0] != target.shape[0]:
        raise ValueError(f"nnls needs A (M, N) and b (M,), got {matrix.shape} and "
                         f"{target.shape}.")
    solution, residual, info = _raw_nnls(matrix, target, 3 * matrix.shape[1])
    if info == 3:
        raise RuntimeError("Maximum number of iterations reached.")
    return solution, residual
