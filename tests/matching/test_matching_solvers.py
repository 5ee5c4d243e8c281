"""SciPy's solvers reached without scipy.optimize, and neighbour searches without scipy.spatial:
the same answers as the public SciPy functions, bit for bit, and a `cblrs track` process that
imports neither package."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cblrs.matching import neighbours, solvers
from cblrs.matching.fusion import gaussian

# SciPy is imported in the tests that compare with it, not at the top: every pytest-xdist
# worker collects this file, and scipy.optimize and scipy.spatial cost about 0.6 CPU-s there.


def test_assignment_is_scipys():
    import scipy.optimize

    generator = np.random.default_rng(1)
    for shape in [(1, 1), (3, 3), (4, 7), (7, 4), (12, 12)]:
        # Integer costs: many ties, where only the same algorithm picks the same answer.
        cost = generator.integers(0, 4, shape).astype(np.float64)
        rows, columns = solvers.linear_sum_assignment(cost)
        expected_rows, expected_columns = scipy.optimize.linear_sum_assignment(cost)
        np.testing.assert_array_equal(rows, expected_rows)
        np.testing.assert_array_equal(columns, expected_columns)
    with pytest.raises(ValueError):
        solvers.linear_sum_assignment(np.full((2, 2), np.nan))


def test_nnls_is_scipys():
    import scipy.optimize

    generator = np.random.default_rng(2)
    for size in (2, 4, 6):
        matrix = generator.normal(size=(size + 3, size))
        target = generator.normal(size=size + 3)
        solution, residual = solvers.nnls(matrix, target)
        expected, expected_residual = scipy.optimize.nnls(matrix, target)
        assert solution.tobytes() == expected.tobytes() and residual == expected_residual
        assert (solution >= 0).all() and (solution == 0).any()  # constraints were active
    with pytest.raises(ValueError):
        solvers.nnls(np.array([[1.0, np.inf]]), np.array([1.0]))
    with pytest.raises(ValueError, match="nnls needs"):
        solvers.nnls(np.eye(2), np.ones(3))


def _grid_points(generator, count: int, dimensions: int) -> np.ndarray:
    """Points on a 0.1 grid (many distances exactly at the radius), some nudged by an ulp."""
    points = generator.integers(-20, 20, (count, dimensions)) * 0.1
    return points + generator.choice([0.0, 0.0, 1e-16, -1e-16], (count, dimensions))


def test_chebyshev_pairs_are_the_trees():
    from scipy.spatial import cKDTree

    generator = np.random.default_rng(3)
    for trial in range(200):
        query = _grid_points(generator, int(generator.integers(0, 120)), 3)
        points = _grid_points(generator, int(generator.integers(1, 120)), 3)
        radius = float(generator.choice([0.1 * 3, 0.5, 0.7]))
        found = sorted(zip(*(side.tolist() for side in
                             neighbours.chebyshev_pairs(query, points, radius)), strict=True))
        near = cKDTree(points).query_ball_point(query, radius, p=np.inf) if len(query) else []
        expected = sorted((row, column) for row, columns in enumerate(near)
                          for column in columns)
        assert found == expected, trial
    assert sum(len(side) for side in neighbours.chebyshev_pairs(query, points, 0.5)) > 0


def test_chebyshev_pairs_beyond_the_sweep_use_the_tree(monkeypatch):
    generator = np.random.default_rng(4)
    query, points = _grid_points(generator, 50, 3), _grid_points(generator, 60, 3)
    swept = neighbours.chebyshev_pairs(query, points, 0.5)
    monkeypatch.setattr(neighbours, "DENSE_PAIRS", 0)
    from_tree = neighbours.chebyshev_pairs(query, points, 0.5)
    assert sorted(zip(*swept, strict=True)) == sorted(zip(*from_tree, strict=True))
    assert len(swept[0]) > 0


@pytest.mark.parametrize("strict", [False, True])
def test_close_pairs_without_the_tree_are_the_trees(monkeypatch, strict):
    generator = np.random.default_rng(5)
    points = _grid_points(generator, 180, 2)  # 180 x 150 pairs: beyond the dense matrix
    points[3] = np.nan
    targets = _grid_points(generator, 150, 2)
    radius = generator.choice([0.1 * 3, 0.5, np.sqrt(0.02)], 180)
    without_tree = gaussian.close_pairs(points, targets, radius, strict)
    monkeypatch.setattr(gaussian, "_TREE_FREE_PAIRS", 0)
    with_tree = gaussian.close_pairs(points, targets, radius, strict)
    for mine, theirs in zip(without_tree, with_tree, strict=True):
        np.testing.assert_array_equal(mine, theirs)
    assert len(with_tree[0]) > 100


def test_track_process_imports_neither_scipy_optimize_nor_spatial(wildtrack_root, tmp_path):
    """The whole `cblrs track` on WILDTRACK, in a fresh process: SciPy's heavy packages are
    never imported (each is a quarter of a second of every run)."""
    script = (
        "import json, sys\n"
        "from cblrs.cli.main import main\n"
        f"code = main(['track', '--dataset', {str(wildtrack_root)!r},"
        f" '--out', {str(tmp_path / 't.txt')!r}, '--quiet'])\n"
        "print(json.dumps([code, sorted(name for name in sys.modules"
        " if name.startswith(('scipy.optimize', 'scipy.spatial', 'scipy.linalg')))]))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    code, loaded = json.loads(done.stdout.strip().splitlines()[-1])
    assert code == 0 and (tmp_path / "t.txt").stat().st_size > 0
    # Only the two compiled solvers, loaded on their own.
    assert set(loaded) <= {"scipy.optimize._lsap", "scipy.optimize._slsqplib"}, loaded
