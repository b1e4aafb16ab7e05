"""Dataset loaders: the real generic layout and UAV123 annotations from ../shared/data, generated OTB/UAVDT trees."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacf.eval.datasets import detect_layout, load_sequences, match, read_boxes, write_boxes
from tacf.eval.datasets import uav123
from tacf.eval.datasets.uav123 import read_ranges
from tacf.images import IMAGE_SUFFIXES

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = DATA / "sequences"
ANNOTATIONS = DATA / "annotations"
needs_data = pytest.mark.skipif(not SEQUENCES.is_dir() or not ANNOTATIONS.is_dir(),
                                reason="../shared/data is absent")

JPG = cv2.imencode(".jpg", np.zeros((4, 6, 3), np.uint8))[1].tobytes()


def write_frames(folder: Path, count: int, fmt: str = "{:06d}.jpg") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(1, count + 1):
        (folder / fmt.format(i)).write_bytes(JPG)


def test_a_glob_without_a_slash_matches_a_name_s_last_part_too():
    """`--sequences person12_1` found nothing: the names are UAV123_10fps/person12_1 and the like."""
    name = "UAV123_10fps/person12_1"
    assert all(match(name, glob) for glob in ("person12_1", "person*", "UAV123*", "UAV123_10fps/*", "x, person12_1"))
    assert not any(match(name, glob) for glob in ("person", "*/person", "DTB70/person12_1", "UAV123_10fps"))
    assert match("S0601", "S06*") and match("S0601", None)


# --- box files -----------------------------------------------------------------------------------------------
def test_read_boxes_separators_nan_and_one_based(tmp_path):
    f = tmp_path / "gt.txt"
    f.write_text("11,21,5,6\n12\t22\t5\t6\n13 22 5 6\nNaN,NaN,NaN,NaN\n\n14, 23, 5.5, 6\n")
    boxes = read_boxes(f)
    assert boxes.shape == (5, 4)
    np.testing.assert_array_equal(boxes[0], [10, 20, 5, 6])
    np.testing.assert_array_equal(boxes[2], [12, 21, 5, 6])
    assert np.isnan(boxes[3]).all()
    np.testing.assert_array_equal(read_boxes(f, one_based=False)[0], [11, 21, 5, 6])


def test_files_saved_by_windows_notepad_are_read(tmp_path):
    """Notepad writes a byte-order mark first: the first box was "not a number" (a ground truth refused by `tacf
    eval`, ignored by `tacf demo` with a warning), an OTB attrs.txt gained a code "\ufeffIV"."""
    from tacf.eval.attributes import read_attribute_list

    gt, attrs = tmp_path / "groundtruth_rect.txt", tmp_path / "attrs.txt"
    gt.write_bytes("11,21,5,6\r\n12,22,5,6\r\n".encode("utf-8-sig"))
    attrs.write_bytes("IV,SV\r\n".encode("utf-8-sig"))
    np.testing.assert_array_equal(read_boxes(gt), [[10, 20, 5, 6], [11, 21, 5, 6]])
    assert read_attribute_list(attrs) == {"IV", "SV"}


def test_read_boxes_rejects_garbage(tmp_path):
    f = tmp_path / "gt.txt"
    f.write_text("1,2,3\n")
    with pytest.raises(ValueError, match="gt.txt:1"):
        read_boxes(f)


def test_write_boxes_round_trip_is_one_based(tmp_path):
    boxes = np.array([[0.0, 1.5, 10, 20], [np.nan] * 4])
    write_boxes(tmp_path / "r" / "s.txt", boxes)
    lines = (tmp_path / "r" / "s.txt").read_text().splitlines()
    assert lines[0] == "1.000,2.500,10.000,20.000"
    np.testing.assert_array_equal(read_boxes(tmp_path / "r" / "s.txt")[0], boxes[0])


# --- generic layout (real data) --------------------------------------------------------------------------------
@needs_data
def test_generic_layout_real_sequences():
    assert detect_layout(SEQUENCES) == "generic"
    seqs = load_sequences(SEQUENCES)
    names = [s.name for s in seqs]
    assert len(seqs) == 15
    assert "UAV123_10fps/wakeboard7" in names and "VOT/bag" in names and "OTB100/Jogging-1" in names
    wb = seqs[names.index("UAV123_10fps/wakeboard7")]
    assert len(wb) == 67 and wb.frames[0].name == "000001.jpg" and wb.frames[-1].name == "000067.jpg"
    np.testing.assert_array_equal(wb.gt[0], [622, 298, 11, 38])       # file: 623,299,11,38
    bag = seqs[names.index("VOT/bag")]
    np.testing.assert_allclose(bag.gt[0], [291.23, 127.36, 145.96, 132.47])   # groundtruth.txt, not the polygon
    assert [s.name for s in load_sequences(SEQUENCES, "UAV123*/wake*,UAVDT/*")] == [
        "UAV123_10fps/wakeboard10", "UAV123_10fps/wakeboard7", "UAVDT/S0601"]
    one = load_sequences(SEQUENCES / "UAVDT" / "S0601")
    assert [s.name for s in one] == ["S0601"] and len(one[0]) == 82


# --- official UAV123 layout: real annotation files and range table, generated frames -------------------------
UAV_FOLDERS = {"bird1": ["bird1_1", "bird1_2", "bird1_3"], "car1": ["car1_1", "car1_2", "car1_3"],
               "wakeboard7": ["wakeboard7"]}


def make_uav123(root: Path, with_table: bool = True) -> dict:
    ranges = read_ranges(ANNOTATIONS / "UAV123_10fps_ranges.txt")
    for folder, names in UAV_FOLDERS.items():
        write_frames(root / "data_seq" / "UAV123_10fps" / folder, max(ranges[None, n].last for n in names) + 3)
        for n in names:
            (root / "anno" / "UAV123_10fps").mkdir(parents=True, exist_ok=True)
            shutil.copy(ANNOTATIONS / "UAV123_10fps" / f"{n}.txt", root / "anno" / "UAV123_10fps" / f"{n}.txt")
    if with_table:
        shutil.copy(ANNOTATIONS / "UAV123_10fps_ranges.txt", root / "UAV123_10fps_ranges.txt")
    return ranges


@needs_data
def test_uav123_layout_honours_frame_ranges(tmp_path):
    ranges = make_uav123(tmp_path)
    assert detect_layout(tmp_path) == "uav123"
    seqs = {s.name: s for s in load_sequences(tmp_path)}
    assert sorted(seqs) == sorted(f"UAV123_10fps/{n}" for names in UAV_FOLDERS.values() for n in names)
    for name, seq in seqs.items():
        r = ranges[None, name.split("/")[1]]
        gt = read_boxes(ANNOTATIONS / "UAV123_10fps" / f"{r.name}.txt")
        assert len(seq) == r.last - r.first + 1 == len(gt)
        assert seq.frames[0] == tmp_path / "data_seq" / "UAV123_10fps" / r.folder / f"{r.first:06d}.jpg"
        assert seq.frames[-1].name == f"{r.last:06d}.jpg"
        np.testing.assert_array_equal(seq.gt, gt)
    assert seqs["UAV123_10fps/bird1_2"].frames[0].name == "000259.jpg"      # a range after a gap
    assert np.isnan(seqs["UAV123_10fps/bird1_1"].gt).any()                  # NaN rows are kept


@needs_data
def test_uav123_range_missing_its_first_frame_is_skipped(tmp_path, caplog):
    make_uav123(tmp_path)
    (tmp_path / "data_seq" / "UAV123_10fps" / "bird1" / "000259.jpg").unlink()   # bird1_2's first frame
    names = [s.name for s in load_sequences(tmp_path)]
    # its ground truth's first row would meet frame 260, and every row the frame after its own
    assert "UAV123_10fps/bird1_2" not in names and "UAV123_10fps/bird1_1" in names
    assert "UAV123_10fps/bird1_2: frame 259 missing from" in caplog.text


@needs_data
def test_uav123_range_table_from_configseqs_and_none(tmp_path):
    make_uav123(tmp_path, with_table=False)
    seqs = [s.name for s in load_sequences(tmp_path)]
    assert seqs == ["UAV123_10fps/wakeboard7"]     # split sequences need a table: skipped with a warning
    (tmp_path / "configSeqs.m").write_text(
        "function seqs=configSeqs\nseqUAV123_10fps = {"
        "struct('name','car1_2','path','D:\\data_seq\\UAV123_10fps\\car1\\','startFrame',251,'endFrame',543,"
        "'nz',6,'ext','jpg','init_rect',[0,0,0,0]),...\n};\n")
    seqs = {s.name: s for s in load_sequences(tmp_path)}
    assert sorted(seqs) == ["UAV123_10fps/car1_2", "UAV123_10fps/wakeboard7"]
    assert seqs["UAV123_10fps/car1_2"].frames[0].name == "000251.jpg" and len(seqs["UAV123_10fps/car1_2"]) == 293
    explicit = load_sequences(tmp_path, ranges=ANNOTATIONS / "UAV123_10fps_ranges.txt")
    assert len(explicit) == 7


@needs_data
def test_all_123_uav123_10fps_sequences_load_as_the_ranges_table_says(tmp_path, monkeypatch):
    ranges = read_ranges(ANNOTATIONS / "UAV123_10fps_ranges.txt")
    frames = {folder: max(r.last for r in ranges.values() if r.folder == folder) + 2
              for folder in {r.folder for r in ranges.values()}}
    data_seq = tmp_path / "data_seq" / "UAV123_10fps"
    data_seq.mkdir(parents=True)
    # 38,000 frame files would take seconds to write: their listing stands in for them
    monkeypatch.setattr(uav123, "list_frames", lambda folder: [folder / f"{i:06d}.jpg" for i in range(
        1, frames[folder.name] + 1)] if folder.parent == data_seq and folder.name in frames else [])
    shutil.copytree(ANNOTATIONS / "UAV123_10fps", tmp_path / "anno" / "UAV123_10fps")
    shutil.copy(ANNOTATIONS / "UAV123_10fps_ranges.txt", tmp_path)
    seqs = load_sequences(tmp_path)
    assert [s.name for s in seqs] == sorted(f"UAV123_10fps/{name}" for _, name in ranges)
    for seq in seqs:
        r = ranges[None, seq.name.split("/")[1]]
        assert [p.name for p in (seq.frames[0], seq.frames[-1])] == [f"{r.first:06d}.jpg", f"{r.last:06d}.jpg"]
        assert seq.frames[0].parent.name == r.folder and len(seq) == r.last - r.first + 1
        np.testing.assert_array_equal(seq.gt, read_boxes(ANNOTATIONS / "UAV123_10fps" / f"{r.name}.txt"))


def test_uav20l_loads_from_the_uav123_folders_of_the_official_release(tmp_path, caplog):
    # The release keeps UAV20L's frames in data_seq/UAV123/ and its configSeqs.m points there; bike1 is in both sets.
    write_frames(tmp_path / "data_seq" / "UAV123" / "bike1", 9)
    write_frames(tmp_path / "data_seq" / "UAV123" / "group1", 7)
    for set_name, name, rows in (("UAV123", "bike1", 5), ("UAV20L", "bike1", 9), ("UAV20L", "group1", 7)):
        (tmp_path / "anno" / set_name).mkdir(parents=True, exist_ok=True)
        (tmp_path / "anno" / set_name / f"{name}.txt").write_text("11,21,5,6\n" * rows)
    assert sorted(s.name for s in load_sequences(tmp_path)) == ["UAV123/bike1", "UAV20L/bike1", "UAV20L/group1"]

    def entry(name, first, last):
        return (f"struct('name','{name}','path','D:\\data_seq\\UAV123\\{name}\\','startFrame',{first},"
                f"'endFrame',{last},'nz',6,'ext','jpg','init_rect',[0,0,0,0])")
    (tmp_path / "configSeqs.m").write_text(
        f"function seqs=configSeqs\nseqUAV123={{{entry('bike1', 3, 7)},...\n}};\n"
        f"seqUAV20L={{{entry('bike1', 1, 9)},...\n{entry('group1', 1, 7)}}};\nseqs=seqUAV123;\n")
    caplog.clear()
    seqs = {s.name: s for s in load_sequences(tmp_path)}
    assert sorted(seqs) == ["UAV123/bike1", "UAV20L/bike1", "UAV20L/group1"] and "skipped" not in caplog.text
    assert [p.name for p in seqs["UAV123/bike1"].frames] == [f"{i:06d}.jpg" for i in range(3, 8)]  # its own range
    assert len(seqs["UAV20L/bike1"]) == 9 and len(seqs["UAV20L/group1"]) == 7
    assert seqs["UAV20L/group1"].frames[0] == tmp_path / "data_seq" / "UAV123" / "group1" / "000001.jpg"
    # Without the table, frames in two releases' folders: which of them is UAV20L's is not guessed
    (tmp_path / "configSeqs.m").unlink()
    write_frames(tmp_path / "data_seq" / "UAV123_10fps" / "group1", 3)
    assert "UAV20L/group1" not in [s.name for s in load_sequences(tmp_path)]
    assert "frames in data_seq/UAV123/group1 and data_seq/UAV123_10fps/group1; a range table's path" in caplog.text


def test_uav123_text_range_table_and_frames_named_without_numbers(tmp_path):
    """A `name folder first last` table (the real one is in ../shared/data, absent from a clean clone): each range
    its own frames, by the numbers in their names, or by position in a folder whose names carry none."""
    write_frames(tmp_path / "data_seq" / "UAV123_10fps" / "group1", 6)
    names = [f"frame_{letter}.jpg" for letter in "abcdef"]
    (tmp_path / "data_seq" / "UAV123_10fps" / "car").mkdir()
    for name in names:
        (tmp_path / "data_seq" / "UAV123_10fps" / "car" / name).write_bytes(JPG)
    (tmp_path / "anno" / "UAV123_10fps").mkdir(parents=True)
    for name in ("group1_1", "group1_2", "car_2"):
        (tmp_path / "anno" / "UAV123_10fps" / f"{name}.txt").write_text("11,21,5,6\n" * 3)
    (tmp_path / "UAV123_10fps_ranges.txt").write_text(
        "# name folder first_frame last_frame\ngroup1_1 group1 1 3\ngroup1_2 group1 4 6\ncar_2 car 3 5\n")
    seqs = {s.name: s for s in load_sequences(tmp_path)}
    assert sorted(seqs) == ["UAV123_10fps/car_2", "UAV123_10fps/group1_1", "UAV123_10fps/group1_2"]
    assert [p.name for p in seqs["UAV123_10fps/group1_1"].frames] == ["000001.jpg", "000002.jpg", "000003.jpg"]
    assert [p.name for p in seqs["UAV123_10fps/group1_2"].frames] == ["000004.jpg", "000005.jpg", "000006.jpg"]
    assert [p.name for p in seqs["UAV123_10fps/car_2"].frames] == names[2:5]


def test_uav123_real_table_parses():
    if not ANNOTATIONS.is_dir():
        pytest.skip("../shared/data is absent")
    ranges = read_ranges(ANNOTATIONS / "UAV123_10fps_ranges.txt")
    assert len(ranges) == 123
    group1_2 = ranges[None, "group1_2"]
    assert (group1_2.set_folder, group1_2.folder, group1_2.first, group1_2.last) == ("UAV123_10fps", "group1", 445, 839)


# --- OTB (generated) -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("sep", [",", "\t", " "])
def test_otb_layout_each_separator(tmp_path, sep):
    write_frames(tmp_path / "Boy" / "img", 3, "{:04d}.jpg")
    (tmp_path / "Boy" / "groundtruth_rect.txt").write_text(
        "\n".join(sep.join(str(v) for v in row) for row in [[1, 2, 3, 4], [5, 6, 7, 8], [9, 10, 11, 12]]) + "\n")
    write_frames(tmp_path / "Jogging" / "img", 2, "{:04d}.jpg")
    (tmp_path / "Jogging" / "groundtruth_rect.1.txt").write_text(f"1{sep}1{sep}5{sep}5\n2{sep}2{sep}5{sep}5\n")
    (tmp_path / "Jogging" / "groundtruth_rect.2.txt").write_text(f"9{sep}9{sep}5{sep}5\n8{sep}8{sep}5{sep}5\n")
    assert detect_layout(tmp_path) == "otb"
    seqs = {s.name: s for s in load_sequences(tmp_path)}
    assert sorted(seqs) == ["Boy", "Jogging-1", "Jogging-2"]
    np.testing.assert_array_equal(seqs["Boy"].gt, [[0, 1, 3, 4], [4, 5, 7, 8], [8, 9, 11, 12]])
    assert [p.name for p in seqs["Boy"].frames] == ["0001.jpg", "0002.jpg", "0003.jpg"]
    np.testing.assert_array_equal(seqs["Jogging-2"].gt[0], [8, 8, 5, 5])


def test_otb_david_starts_at_frame_300(tmp_path):
    write_frames(tmp_path / "David" / "img", 310, "{:04d}.jpg")
    (tmp_path / "David" / "groundtruth_rect.txt").write_text("1,1,5,5\n" * 11)
    (seq,) = load_sequences(tmp_path)
    assert len(seq) == 11 and seq.frames[0].name == "0300.jpg"


def test_otb_david_cut_to_its_annotated_frames_starts_at_its_first(tmp_path):
    """A copy holding only the frames the ground truth covers (0300-0310 for 11 rows) is not cut again."""
    (tmp_path / "David" / "img").mkdir(parents=True)
    for number in range(300, 311):
        (tmp_path / "David" / "img" / f"{number:04d}.jpg").write_bytes(JPG)
    (tmp_path / "David" / "groundtruth_rect.txt").write_text("1,1,5,5\n" * 11)
    (seq,) = load_sequences(tmp_path)
    assert len(seq) == 11 and seq.frames[0].name == "0300.jpg"


def test_otb_david_given_as_dot_or_dot_dot_still_starts_at_frame_300(tmp_path, monkeypatch):
    """`tacf eval .` in David's folder (or `..` from its img/) matched the ground truth with frames 1 to 11."""
    write_frames(tmp_path / "David" / "img", 310, "{:04d}.jpg")
    (tmp_path / "David" / "groundtruth_rect.txt").write_text("1,1,5,5\n" * 11)
    for cwd, root in ((tmp_path / "David", "."), (tmp_path / "David" / "img", "..")):
        monkeypatch.chdir(cwd)
        (seq,) = load_sequences(Path(root))
        assert seq.name == "David" and seq.frames[0].name == "0300.jpg", root


# --- UAVDT (generated, official layout) -----------------------------------------------------------------------
def test_uavdt_layout(tmp_path):
    for name, n in (("S0101", 4), ("S0102", 3)):
        write_frames(tmp_path / "UAV-benchmark-S" / name, n, "img{:06d}.jpg")
    anno = tmp_path / "UAV-benchmark-SOT_v1.0" / "anno"
    (anno / "att").mkdir(parents=True)
    (anno / "S0101_gt.txt").write_text("11,21,5,6\n" * 4)
    (anno / "S0102_gt.txt").write_text("1,1,5,6\n" * 3)
    (anno / "att" / "S0101_att.txt").write_text("1,0,0,0,0,0,0,0\n")
    assert detect_layout(tmp_path) == "uavdt"
    seqs = load_sequences(tmp_path)
    assert [s.name for s in seqs] == ["UAVDT/S0101", "UAVDT/S0102"]
    assert len(seqs[0]) == 4 and seqs[0].frames[0].name == "img000001.jpg"
    np.testing.assert_array_equal(seqs[0].gt[0], [10, 20, 5, 6])
    assert [s.name for s in load_sequences(tmp_path / "UAV-benchmark-S", "*0102")] == ["UAVDT/S0102"]


def test_unknown_layout_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no known dataset layout"):
        detect_layout(tmp_path)
    with pytest.raises(FileNotFoundError):
        detect_layout(tmp_path / "missing")


def test_a_frame_missing_on_disk_skips_its_sequence_instead_of_shifting_the_ground_truth(tmp_path, caplog):
    for name in ("gap", "whole", "extra"):
        write_frames(tmp_path / name / "img", 6)
        (tmp_path / name / "groundtruth.txt").write_text("".join(f"{i},1,5,5\n" for i in range(1, 6)))
    (tmp_path / "gap" / "img" / "000003.jpg").unlink()    # frame 4 would meet the box of frame 3
    (tmp_path / "extra" / "img" / "000006.jpg").unlink()  # past the ground truth's 5 rows: no harm
    seqs = load_sequences(tmp_path)
    assert [s.name for s in seqs] == ["extra", "whole"]
    assert "gap: frame 3 missing from" in caplog.text
    write_frames(tmp_path / "stamps" / "img", 0)
    for stamp in (1000, 1033, 1067):                      # time-stamped names: no numbering to check
        (tmp_path / "stamps" / "img" / f"{stamp}.jpg").write_bytes(JPG)
    (tmp_path / "stamps" / "groundtruth.txt").write_text("1,1,5,5\n" * 3)
    assert "stamps" in [s.name for s in load_sequences(tmp_path)]


def test_a_missing_first_frame_skips_its_sequence_in_the_generic_and_uavdt_layouts(tmp_path, caplog):
    """Only the UAV123 layout noticed it (its range table gives the first frame's number): elsewhere every row of
    the ground truth met the frame after its own."""
    for name in ("headless", "clip"):
        write_frames(tmp_path / "generic" / name / "img", 6)
        (tmp_path / "generic" / name / "img" / "000001.jpg").unlink()
    (tmp_path / "generic" / "headless" / "groundtruth.txt").write_text("1,1,5,5\n" * 6)
    (tmp_path / "generic" / "clip" / "groundtruth.txt").write_text("1,1,5,5\n" * 5)   # a clip numbered from 2
    write_frames(tmp_path / "generic" / "zero" / "img", 0)
    for i in range(5):                                                        # numbered from 0: nothing missing
        (tmp_path / "generic" / "zero" / "img" / f"{i}.jpg").write_bytes(JPG)
    (tmp_path / "generic" / "zero" / "groundtruth.txt").write_text("1,1,5,5\n" * 6)
    assert [s.name for s in load_sequences(tmp_path / "generic")] == ["clip", "zero"]
    assert "headless: frame 1 missing from" in caplog.text
    for name in ("S0101", "S0102"):
        write_frames(tmp_path / "uavdt" / "UAV-benchmark-S" / name, 4, "img{:06d}.jpg")
        (tmp_path / "uavdt" / "UAV-benchmark-SOT_v1.0" / "anno").mkdir(parents=True, exist_ok=True)
        (tmp_path / "uavdt" / "UAV-benchmark-SOT_v1.0" / "anno" / f"{name}_gt.txt").write_text("1,1,5,6\n" * 4)
    (tmp_path / "uavdt" / "UAV-benchmark-S" / "S0102" / "img000001.jpg").unlink()
    assert [s.name for s in load_sequences(tmp_path / "uavdt")] == ["UAVDT/S0101"]
    assert "UAVDT/S0102: frame 1 missing from" in caplog.text


def test_a_vot_polygon_row_is_read_as_its_enclosing_box(tmp_path):
    write_frames(tmp_path / "bag", 2, "{:08d}.jpg")                 # the official VOT layout: frames beside it
    (tmp_path / "bag" / "groundtruth.txt").write_text("334.02,128.36,438.19,188.78,396.39,260.83,292.23,200.41\n"
                                                      "nan,nan,nan,nan,nan,nan,nan,nan\n")
    (seq,) = load_sequences(tmp_path)
    np.testing.assert_allclose(seq.gt[0], [291.23, 127.36, 145.96, 132.47])   # not x 333.02, w 438.19
    assert np.isnan(seq.gt[1]).all()


def test_the_vot_toolkit_layout_of_2020_on_reads_its_color_frames(tmp_path, caplog):
    write_frames(tmp_path / "bag" / "color", 2, "{:08d}.jpg")
    write_frames(tmp_path / "bag" / "depth", 2, "{:08d}.png")       # an RGB-D sequence's other channel: ignored
    (tmp_path / "bag" / "sequence").write_text("channels.color=color/%08d.jpg\nchannels.depth=depth/%08d.png\n")
    (tmp_path / "bag" / "groundtruth.txt").write_text("292.23,128.36,145.96,132.47\n" * 2)
    (seq,) = load_sequences(tmp_path)
    assert seq.name == "bag" and [p.parent.name for p in seq.frames] == ["color", "color"]
    write_frames(tmp_path / "ants" / "color", 2, "{:08d}.jpg")
    (tmp_path / "ants" / "groundtruth.txt").write_text("m10,10,4,3,2,5,5\n" * 2)  # VOT-ST's masks
    with pytest.raises(ValueError, match="ants/groundtruth.txt:1: a VOT segmentation mask; tacf evaluates boxes"):
        load_sequences(tmp_path)


@needs_data
def test_vot_polygons_give_the_axis_aligned_ground_truth_shipped_beside_them():
    bag = SEQUENCES / "VOT" / "bag"
    np.testing.assert_allclose(read_boxes(bag / "groundtruth_poly.txt"), read_boxes(bag / "groundtruth.txt"),
                               atol=1e-9)


def test_an_empty_ground_truth_file_skips_its_sequence(tmp_path, caplog):
    for name in ("empty", "full"):
        write_frames(tmp_path / name / "img", 2)
    (tmp_path / "empty" / "groundtruth.txt").write_text("")
    (tmp_path / "full" / "groundtruth.txt").write_text("1,1,5,5\n" * 2)
    assert [s.name for s in load_sequences(tmp_path)] == ["full"]
    assert "empty: 2 frames and 0 ground-truth rows, nothing to track; skipped" in caplog.text


def test_a_folder_with_ground_truth_but_no_frames_is_named_in_a_warning(tmp_path, caplog):
    """It was left out without a word, unlike a UAV123 sequence without frames. The suffixes read are those of
    `tacf publish` and `tacf track` (tacf.images): TIFF frames were refused here alone."""
    write_frames(tmp_path / "jpg" / "img", 2)
    write_frames(tmp_path / "tiff" / "img", 2, "{:06d}.tif")
    write_frames(tmp_path / "gif" / "img", 2, "{:06d}.gif")       # a suffix not read
    for name in ("jpg", "tiff", "gif"):
        (tmp_path / name / "groundtruth.txt").write_text("1,1,5,5\n" * 2)
    assert [s.name for s in load_sequences(tmp_path)] == ["jpg", "tiff"]
    suffixes = ", ".join(IMAGE_SUFFIXES)
    assert f"gif: ground truth but no frames ({suffixes} files) in {tmp_path / 'gif'}" in caplog.text


@needs_data
def test_a_sequence_folder_given_as_dot_or_dot_dot_keeps_its_name(monkeypatch):
    """`tacf eval .` in a sequence folder named the sequence "": results in a hidden `<tracker>/.txt`, and
    `--sequences wakeboard7` matched nothing; `..` from its img/ named it ".."."""
    folder = SEQUENCES / "UAV123_10fps" / "wakeboard7"
    for cwd, root in ((folder, "."), (folder / "img", ".."), (folder, "../wakeboard7")):
        monkeypatch.chdir(cwd)
        (seq,) = load_sequences(Path(root), "wakeboard7")
        assert seq.name == "wakeboard7" and len(seq) == 67, root
