"""Sequence attributes: UAV123's definitions on hand-made tracks, its att files, the --attributes table, and the
per-attribute scores of a summary."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tacf.eval.attributes import (OTB_ATTRIBUTES, UAV123_ATTRIBUTES, attributes_of, derived_attributes,
                                  read_attribute_table, read_uav123_flags)
from tacf.eval.datasets import Sequence, load_sequences
from tacf.eval.report import attribute_scores, attribute_table

STILL = [100.0, 100.0, 40.0, 40.0]


def track(*boxes) -> np.ndarray:
    return np.array([STILL, *boxes], dtype=np.float64)


def around(w: float, h: float, dx: float = 0.0, dy: float = 0.0) -> list[float]:
    """A w x h box centred where STILL is, moved by (dx, dy)."""
    return [120.0 - w / 2 + dx, 120.0 - h / 2 + dy, w, h]


@pytest.mark.parametrize("later,expected", [
    (around(40, 40), set()),
    (around(81, 81), {"SV"}),                       # scale 2.025 times the first box's
    (around(79, 79), set()),                        # 1.975 times
    (around(19, 19), {"SV", "LR"}),                 # under half, and 361 pixels
    (around(20, 20), set()),                        # exactly half the side, 400 pixels: neither
    (around(81, 19), {"ARC"}),                      # aspect 4.26, scale 0.98, 1,539 pixels
    (around(57, 28), {"ARC"}),                      # aspect 2.04 times the first's
    (around(40, 40, dx=21), {"FM"}),                # the centre moved 21 px
    (around(40, 40, dx=14, dy=14), set()),          # 19.8 px
])
def test_uav123_s_definitions_on_hand_made_tracks(later, expected):
    assert derived_attributes(track(later)) == frozenset(expected)


def test_absent_frames_break_a_move_and_a_track_without_boxes_has_nothing():
    far = [300.0, 300.0, 40.0, 40.0]
    assert derived_attributes(track([math.nan] * 4, far)) == frozenset()   # no two consecutive frames present
    assert derived_attributes(track(far)) == frozenset({"FM"})
    assert derived_attributes(np.full((3, 4), math.nan)) == frozenset()
    assert derived_attributes(track([100.0, 100.0, 0.0, 0.0])) == frozenset()  # a zero box counts as absent


def refused(read, path, text: str, message: str) -> None:
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read(path)


def test_uav123_att_files_name_the_flags_in_the_toolkit_s_order(tmp_path):
    flags = tmp_path / "bike1.txt"
    flags.write_text("1,0,0,1,0,0,0,0,0,0,1,1\n")
    assert read_uav123_flags(flags) == frozenset({"SV", "FM", "CM", "SOB"})
    assert list(UAV123_ATTRIBUTES)[:4] == ["SV", "ARC", "LR", "FM"]
    refused(read_uav123_flags, flags, "1,0,1\n", "expected 12 0/1 flags, got 3")
    refused(read_uav123_flags, flags, "1,0,x,0,0,0,0,0,0,0,0,0\n", "expected 12 0/1 flags")


def test_the_uav123_loader_reads_the_att_files_beside_the_annotations(tmp_path):
    image = cv2.imencode(".jpg", np.zeros((4, 6, 3), np.uint8))[1].tobytes()
    anno = tmp_path / "anno" / "UAV123_10fps"
    (anno / "att").mkdir(parents=True)
    for name in ("boat1", "boat2"):
        frames = tmp_path / "data_seq" / "UAV123_10fps" / name
        frames.mkdir(parents=True)
        for i in range(1, 4):
            (frames / f"{i:06d}.jpg").write_bytes(image)
        (anno / f"{name}.txt").write_text("1,1,2,2\n" * 3)
    (anno / "att" / "boat1.txt").write_text("0,0,0,1,0,0,0,0,0,0,0,0\n")
    seqs = {s.name: s for s in load_sequences(tmp_path)}
    assert seqs["UAV123_10fps/boat1"].attributes == frozenset({"FM"})
    assert seqs["UAV123_10fps/boat2"].attributes is None          # no file: unknown, not "none"
    source, found = attributes_of(seqs.values())
    assert source == "dataset" and found == {"UAV123_10fps/boat1": {"FM"}, "UAV123_10fps/boat2": frozenset()}


def test_otb_folders_carry_their_attributes_in_attrs_txt(tmp_path):
    """The OTB benchmark's Python toolkit keeps each sequence's attributes in its folder: `SV, DEF, FM, OPR, BC`."""
    image = cv2.imencode(".jpg", np.zeros((4, 6, 3), np.uint8))[1].tobytes()
    for name in ("Crossing", "Jogging", "Couple"):
        (tmp_path / name / "img").mkdir(parents=True)
        for i in range(1, 4):
            (tmp_path / name / "img" / f"{i:04d}.jpg").write_bytes(image)
    (tmp_path / "Crossing" / "groundtruth_rect.txt").write_text("1,1,2,2\n" * 3)
    (tmp_path / "Crossing" / "attrs.txt").write_text("SV, DEF, FM, OPR, BC")
    for target in (1, 2):  # a two-target folder: its attributes are both targets'
        (tmp_path / "Jogging" / f"groundtruth_rect.{target}.txt").write_text("1\t1\t2\t2\n" * 3)
    (tmp_path / "Jogging" / "attrs.txt").write_text("OCC, DEF, OPR\n")
    (tmp_path / "Couple" / "groundtruth_rect.txt").write_text("1,1,2,2\n" * 3)
    seqs = {s.name: s for s in load_sequences(tmp_path)}
    assert seqs["Crossing"].attributes == frozenset({"SV", "DEF", "FM", "OPR", "BC"})
    assert seqs["Jogging-1"].attributes == seqs["Jogging-2"].attributes == frozenset({"OCC", "DEF", "OPR"})
    assert seqs["Couple"].attributes is None
    source, found = attributes_of(seqs.values())
    assert source == "dataset" and found["Couple"] == frozenset()
    summary = {"trackers": {"a": {"auc": 0.5, "sequences": {name: {"auc": 0.5, "precision20": 0.5}
                                                             for name in seqs}}}}
    result = attribute_scores(summary, found, source)
    # UAV123's codes in its order first, then OTB's own, each named
    assert list(result["attributes"]) == ["SV", "FM", "BC", "OCC", "DEF", "OPR"]
    assert [result["attributes"][a]["name"] for a in ("BC", "OPR")] == ["background clutter", "out-of-plane rotation"]
    assert len(OTB_ATTRIBUTES) == 11


def test_an_attribute_table_names_sequences_in_full_or_by_their_last_part(tmp_path, caplog):
    table = tmp_path / "attributes.txt"
    table.write_text("# name attributes\nUAV123_10fps/truck2 FM,SOB\nwakeboard7  ARC   # the short name\n\n")
    read = read_attribute_table(table)
    assert read == {"UAV123_10fps/truck2": {"FM", "SOB"}, "wakeboard7": {"ARC"}}
    seqs = [Sequence(name, ["a.jpg"], [STILL]) for name in ("UAV123_10fps/truck2", "UAV123_10fps/wakeboard7",
                                                             "UAVDT/S0601")]
    source, found = attributes_of(seqs, read)
    assert source == "table" and found == {"UAV123_10fps/truck2": {"FM", "SOB"},
                                           "UAV123_10fps/wakeboard7": {"ARC"}, "UAVDT/S0601": frozenset()}
    assert "UAVDT/S0601: not in the attribute table" in caplog.text
    refused(read_attribute_table, table, "a FM\na SV\n", "'a' listed twice")
    refused(read_attribute_table, table, "# nothing\n", "no sequences listed")
    table.write_text("Basketball\tIV, OCC, DEF, OPR, BC\nBiker\tFM, LR\n")  # OTB's own attribute list
    assert read_attribute_table(table) == {"Basketball": {"IV", "OCC", "DEF", "OPR", "BC"}, "Biker": {"FM", "LR"}}


def test_without_labels_the_attributes_are_derived_from_the_ground_truth():
    seqs = [Sequence("fast", ["a.jpg", "b.jpg"], track([160.0, 100.0, 40.0, 40.0])),
            Sequence("still", ["a.jpg", "b.jpg"], track(STILL))]
    assert attributes_of(seqs) == ("derived", {"fast": {"FM"}, "still": frozenset()})


def test_per_attribute_scores_are_means_over_the_attribute_s_sequences():
    summary = {"trackers": {
        "a": {"auc": 0.5, "sequences": {"s1": {"auc": 0.2, "precision20": 0.3}, "s2": {"auc": 0.6, "precision20": 0.9},
                                        "s3": {"auc": 0.7, "precision20": 1.0}}},
        "b": {"auc": 0.6, "sequences": {"s1": {"auc": 0.4, "precision20": 0.5}}}}}
    attributes = {"s1": frozenset({"FM", "custom"}), "s2": frozenset({"FM"}), "s3": frozenset()}
    result = attribute_scores(summary, attributes, "table")
    assert list(result["attributes"]) == ["FM", "custom"]             # UAV123's order first, then by name
    fm = result["attributes"]["FM"]
    assert fm["name"] == "fast motion" and fm["sequences"] == ["s1", "s2"]
    assert fm["trackers"]["a"] == {"auc": pytest.approx(0.4), "precision20": pytest.approx(0.6), "sequences": 2}
    assert fm["trackers"]["b"] == {"auc": pytest.approx(0.4), "precision20": pytest.approx(0.5), "sequences": 1}
    table = attribute_table({**summary, "attributes": result})
    assert "| attribute | sequences | b | a |" in table                 # trackers ranked by their overall AUC
    assert "| FM (fast motion) | 2 | 0.400 | 0.400 |" in table and "| custom (custom) | 1 | 0.400 | 0.200 |" in table
    empty = attribute_scores(summary, {"s1": frozenset()}, "derived")
    assert empty["attributes"] == {} and attribute_table({**summary, "attributes": empty}) == ""
