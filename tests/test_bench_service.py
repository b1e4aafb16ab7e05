"""`tacf bench service` end to end: a real `tacf serve` child, real 1280x720 JPEG sequences, real Zenoh."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from tacf.cli import main

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "sequences"

pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"benchmark sequences not found at {DATA}")


def test_bench_service_reports_latency_drops_memory_and_cpu(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "service", str(DATA), "--feeds", "2", "--fps", "5", "--seconds", "4", "--warmup", "1",
                 "--json", str(out), "--no-progress"]) == 0
    assert "2 feeds:" not in capsys.readouterr().err
    report = json.loads(out.read_text())
    assert report["feeds"] == 2 and report["fps_in"] == 5.0
    assert 2 * 5 * 4 * 0.7 <= report["frames_sent"] <= 2 * 5 * 4 * 1.3   # paced, not flooded
    # every frame got a box or is counted as dropped; at 10 frames/s in all, most get one even on a loaded box
    assert report["boxes_received"] + report["dropped"] == report["frames_sent"]
    assert report["boxes_received"] >= report["frames_sent"] // 2
    latency = report["latency_ms"]
    assert 0 < latency["p50"] <= latency["p95"] <= latency["p99"] <= latency["max"]
    assert report["rss_mb_per_session"] > 50 and report["pss_mb_per_session"] > 10
    assert report["pss_mb_total"] > 2 * report["pss_mb_per_session"]   # the service and its fork server besides
    assert 0 < report["cpu_percent"] <= 100 * report["cpus"]
    over_time = report["over_time"]
    assert len(over_time["seconds"]) == len(over_time["rss_mb"]) == len(over_time["pss_mb"]) == \
        len(over_time["open_fds"]) >= 10
    assert min(over_time["open_fds"]) > 0 and min(over_time["rss_mb"]) > 100
    assert 0 < max(over_time["pss_mb"]) < max(over_time["rss_mb"])
    assert all(name.startswith(("UAV123", "DTB70")) for name in report["sequences"])   # the 1280x720 ones


def test_bench_service_without_sequences_is_a_clear_error(tmp_path, caplog):
    assert main(["bench", "service", str(tmp_path / "nowhere")]) == 2
    assert "does not exist" in caplog.text


def test_bench_service_refuses_a_bad_warmup_or_profile_before_starting_a_service():
    for bad in (["--warmup", "-1"], ["--fps", "nan"], ["--profile", "bogus"], ["--json", str(DATA)]):
        # argparse: a usage error naming what is wrong (a NaN --fps passed a `<= 0` check and ran)
        with pytest.raises(SystemExit) as refused:
            main(["bench", "service", str(DATA), *bad])
        assert refused.value.code == 2
