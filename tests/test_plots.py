"""`stats LOG --plot` and `build --plot`: the drawn series are the measured ones."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli

from voxtool.codec.log import PacketLogWriter, read_log
from voxtool.codec.logstats import log_stats
from voxtool.plots import log_figure


def test_log_plot_draws_each_robots_bandwidth_and_packets(sample_logs, tmp_path):
    # one log holding both robots' packets (robot a: scans 0-2, robot b: scans 3-4)
    both = tmp_path / "both.mcap"
    with PacketLogWriter(both) as out:
        for name in ("a", "b"):
            meta, messages = read_log(sample_logs[name][0])
            for seq, (robot, stamp, blob) in enumerate(messages):
                out.write(robot, seq, stamp, blob)
            out.metadata(name, meta[name])
    series = {}
    stats = log_stats(both, series=series)
    bandwidth, sizes = log_figure(stats, series).axes
    stairs = [p for p in bandwidth.patches]
    assert len(stairs) == 2 == len(sizes.collections)
    t0 = min(int(s.min()) for s, _ in series.values())
    for robot, steps, dots in zip(sorted(series), stairs, sizes.collections):
        row = stats["robots"][robot]
        values = steps.get_data().values * 1e3
        assert values.sum() == pytest.approx(row["bytes"])  # every byte in one window
        assert max(values.max(), row["avg_Bps"]) == pytest.approx(row["max_Bps"], abs=0.1)
        stamps, nbytes = series[robot]
        offsets = dots.get_offsets()
        assert len(offsets) == row["packets"]
        assert np.allclose(offsets[:, 0], (stamps - t0) / 1e9) and np.array_equal(offsets[:, 1], nbytes)
    dashed = sorted(line.get_ydata()[0] for line in bandwidth.lines)
    assert dashed == pytest.approx(sorted(stats["robots"][r]["avg_Bps"] / 1e3 for r in series))
    assert sizes.get_xlim()[1] >= max((s.max() - t0) / 1e9 for s, _ in series.values())


def test_stats_plot_is_refused_for_a_map_and_written_for_a_log(sample_logs, sample_map, tmp_path):
    from matplotlib.image import imread

    plot = tmp_path / "bw.png"
    code, text, err = cli("stats", sample_logs["r1"][0], "--plot", plot, "--json")
    assert code == 0, err
    report = json.loads(text)
    assert imread(plot).shape[:2] == (report["height"], report["width"]) and report["plot"] == str(plot)
    code, _, err = cli("stats", sample_map[0], "--plot", tmp_path / "m.png")
    assert code == 2 and "--plot draws the bandwidth of packet logs" in err and not (tmp_path / "m.png").exists()
    from voxtool.codec.log import PacketLogWriter

    with PacketLogWriter(tmp_path / "empty.mcap") as writer:  # a log closed before its first packet
        writer.metadata("r1", {"scans": 0})
    code, _, err = cli("stats", tmp_path / "empty.mcap", "--plot", tmp_path / "e.png")
    assert code == 2 and err.count("\n") == 1 and "holds no packets" in err and not (tmp_path / "e.png").exists()


def test_stats_plot_draws_several_robots_logs_in_one_plot(sample_logs, tmp_path):
    """Two robots' logs in one bandwidth plot (it was refused); a robot name both logs hold is
    told apart by its file."""
    from matplotlib.image import imread

    from voxtool.codec.logstats import log_stats
    from voxtool.plots import log_figure

    plot = tmp_path / "both.png"
    code, text, err = cli("stats", sample_logs["a"][0], sample_logs["b"][0], "--plot", plot, "--json")
    assert code == 0, err
    report = json.loads(text)
    assert [set(r["robots"]) for r in report["logs"]] == [{"a"}, {"b"}] and imread(plot).shape[0] > 100
    assert report["bytes"] == sum(r["bytes"] for r in report["logs"])
    code, text, err = cli("stats", sample_logs["a"][0], sample_logs["a"][0], "--plot", tmp_path / "twice.png")
    assert code == 0 and "2 robots" in text, err
    series = {}
    stats = log_stats(sample_logs["a"][0], False, series)
    fig = log_figure({**stats, "robots": {"a": stats["robots"]["a"], "b": stats["robots"]["a"]}},
                     {"a": series["a"], "b": series["a"]})
    assert [t.get_text().split(":")[0] for t in fig.axes[0].get_legend().get_texts()] == ["a", "b"]


def test_build_plot_draws_every_scans_latency_and_map_size(tmp_path):
    from matplotlib.image import imread

    from voxtool.api import build_map
    from voxtool.cli.common import resolve_source
    from voxtool.config import MapParams, SensorModel
    from voxtool.plots import build_figure
    from voxtool.sources import SourceOptions

    result = build_map(resolve_source(None, True), SourceOptions(), MapParams(), SensorModel(), per_scan=True)
    latency, size = build_figure(result, "sample").axes
    (lat_line, median), (size_line,) = latency.lines, size.lines
    scans = result["per_scan"]
    assert len(lat_line.get_xdata()) == result["scans"] == len(size_line.get_xdata()) == 5
    assert np.allclose(lat_line.get_ydata(), scans["latency_ms"])
    assert np.mean(scans["latency_ms"]) == pytest.approx(result["scan_latency_ms"]["mean"], rel=1e-3)
    assert median.get_ydata()[0] == result["scan_latency_ms"]["p50"]
    map_mib = size_line.get_ydata()
    assert np.all(np.diff(map_mib) >= 0) and map_mib[-1] * 2**20 == pytest.approx(result["pool_bytes_used"], rel=1e-6)
    plot = tmp_path / "build.png"
    code, text, err = cli("build", "--sample", "--plot", plot, "--json", "--no-progress")
    assert code == 0, err
    report = json.loads(text)
    assert "per_scan" not in report and imread(plot).shape[:2] == (report["height"], report["width"])
