"""The recovery attacks: exact landmarks recover the key exactly, a walkway map nearly."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.cli.main import main
from cblrs.privacy import PseudoKey
from cblrs.privacy.attack import DensityMap, align_to_density, fit_rigid, recovery_error

KEY = PseudoKey(bytes(range(1, 33)), "0000abcd")


def _walkers(seed: int, count: int = 2000) -> np.ndarray:
    """Positions on an L-shaped walkway (no symmetry a rotation could hide behind)."""
    rng = np.random.default_rng(seed)
    along = rng.uniform(0, 30, count)
    leg = rng.random(count) < 0.6
    points = np.where(leg[:, None], np.c_[along, rng.normal(0, 0.6, count)],
                      np.c_[rng.normal(0, 0.6, count), along * 0.5])
    return points


def test_exact_landmarks_give_the_key_back():
    site = np.array([[0.0, 0.0], [10.0, 3.0], [4.0, 12.0]])
    recovered = fit_rigid(KEY.to_pseudo(site), site)
    database = _walkers(0)[:50]
    assert recovery_error(recovered, KEY.to_pseudo(database), database).max() < 1e-6
    # Two landmarks fix a rigid transform too.
    recovered = fit_rigid(KEY.to_pseudo(site[:2]), site[:2])
    assert recovery_error(recovered, KEY.to_pseudo(database), database).max() < 1e-6
    with pytest.raises(ValueError):
        fit_rigid(site[:1], site[:1])


def test_a_footfall_map_recovers_the_transform():
    survey, database = _walkers(1), _walkers(2, 500)
    recovered, _ = align_to_density(KEY.to_pseudo(database), DensityMap.from_points(survey),
                                    coarse_deg=3.0)
    error = recovery_error(recovered, KEY.to_pseudo(database), database)
    assert np.median(error) < 0.5


def test_the_experiment_command_writes_its_table(wildtrack_root, tmp_path, capsys):
    assert main(["experiment", "pseudo", "--dataset", str(wildtrack_root), "--landmarks", "3",
                 "--sigmas", "0.5", "--mast-sigmas", "1", "--draws", "5", "--keys", "1",
                 "--out", str(tmp_path), "--quiet"]) == 0
    text = (tmp_path / "experiment_pseudo.md").read_text()
    assert "| landmarks, error 0.5 m | k = 3 | 5 |" in text
    assert "footfall density" in text and "camera masts" in text
    assert main(["experiment", "pseudo", "--landmarks", "1"]) == 2
    assert "--landmarks must be whole numbers >= 2" in capsys.readouterr().err
