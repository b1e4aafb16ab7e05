"""Reports over hand-made runs: what summary.json says a tracker scored, and how fast it ran."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tacf.eval.datasets import Sequence
from tacf.eval.report import score_runs


def still_sequence(name: str, n: int) -> Sequence:
    return Sequence(name, [Path(f"{name}/{i}.jpg") for i in range(n)], np.tile([10.0, 10.0, 5.0, 5.0], (n, 1)))


def test_fps_counts_only_the_frames_of_the_sequences_that_were_timed():
    timed, untimed = still_sequence("timed", 67), still_sequence("untimed", 129)
    runs = {"timed": (timed.gt, np.full(67, 0.1)), "untimed": (untimed.gt, np.full(129, np.nan))}
    entry = score_runs("imported", [timed, untimed], runs).entry()
    assert entry["fps"] == pytest.approx(10.0) and entry["frames"] == 67 + 129
    assert entry["sequences"]["timed"]["fps"] == pytest.approx(10.0) and np.isnan(entry["sequences"]["untimed"]["fps"])
    assert np.isnan(score_runs("none", [untimed], {"untimed": runs["untimed"]}).entry()["fps"])
