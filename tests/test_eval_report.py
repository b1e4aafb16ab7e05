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


def test_the_table_ranks_the_trackers_by_auc_best_first_and_a_tracker_without_one_last():
    from tacf.eval.report import markdown_table

    def entry(auc):
        return {"auc": auc, "precision20": 0.5, "fps": 10.0, "frames": 5, "sequences": {"s": {"auc": auc}}}

    table = markdown_table({"trackers": {"unscored": entry(float("nan")), "worse": entry(0.4), "better": entry(0.6)}})
    rows = [line.split(" | ")[0] for line in table.splitlines() if line.startswith("| ") and " | 5 | " in line]
    assert rows == ["| better", "| worse", "| unscored"]
    assert "| sequence | better | worse | unscored |" in table


def test_otb_s_tre_pools_each_sequence_s_frames_over_its_starts():
    from tacf.eval.report import robustness, robustness_table

    def summary(s0, s1):  # (auc, precision20) of two sequences
        return {"trackers": {"a": {"sequences": {name: {"auc": auc, "precision20": p20}
                                                 for name, (auc, p20) in (("s0", s0), ("s1", s1))}}}}

    per_start = {"0/2": summary((0.8, 1.0), (0.6, 0.5)), "1/2": summary((0.2, 0.4), (0.6, 0.5))}
    frames = {"0/2": {"s0": 100, "s1": 10}, "1/2": {"s0": 50, "s1": 5}}   # the later start: half the frames
    a = robustness(per_start, ["a"], "tre", frames_scored=frames)["trackers"]["a"]
    assert a["mean"] == pytest.approx(0.55)                   # every start alike: (0.5 + 0.6) / 2, as before
    # s0: (0.8 * 100 + 0.2 * 50) / 150 = 0.6, s1: 0.6; precision s0: (100 + 20) / 150 = 0.8, s1: 0.5
    assert a["otb_pooled"] == pytest.approx({"auc": 0.6, "precision20": 0.65})
    table = robustness_table(robustness(per_start, ["a"], "tre", frames_scored=frames))
    assert "OTB's TRE, pooled: AUC / precision@20 |" in table
    assert "| a | 0.700 | 0.550 | 0.400 - 0.700 | - | 0.600 / 0.650 |" in table
    assert "otb_pooled" not in robustness(per_start, ["a"], "tre")["trackers"]["a"]


@pytest.mark.parametrize("count", [1, 2, 5])
def test_the_robustness_plot_shows_its_whole_title_and_caption(count, tmp_path, monkeypatch):
    """The figure's width followed the number of trackers only: with one or two, the title and the caption that
    says what the dots and the bar are ran off its edges."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from tacf.eval.report import plot_robustness

    saved = []
    savefig = Figure.savefig

    def keep(fig, *args, **kwargs):   # the figure, to measure it after the plot closed it
        saved.append(fig)
        return savefig(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    trackers = {f"tracker{i}": {"auc_per_start": [0.45, 0.52, 0.38], "mean": 0.45} for i in range(count)}
    for protocol in ("shifts", "tre"):
        plot_robustness({"protocol": protocol, "starts": ["a", "b", "c"], "sequences": 10, "trackers": trackers},
                        tmp_path)
        fig = saved[-1]
        renderer = FigureCanvasAgg(fig).get_renderer()
        ax = fig.axes[0]
        for text in (ax.title, ax.xaxis.label):
            extent = text.get_window_extent(renderer)
            assert 0 <= extent.x0 and extent.x1 <= fig.bbox.width, (protocol, text.get_text())
