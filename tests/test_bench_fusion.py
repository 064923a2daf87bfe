"""`d2a bench fusion` at a tiny size: every row is timed."""

from __future__ import annotations

from benchmarks.fusion import FusionBenchConfig, run


def test_bench_fusion_times_full_and_decimated_fusion(capsys):
    results = run(FusionBenchConfig(width=64, height=48, num_points=64, repeats=1))
    assert len(results) == 4 and all(seconds > 0 for seconds in results.values())
    out = capsys.readouterr().out
    assert "every 4th pixel (16 x 12 per frame)" in out and "every 8th pixel (8 x 6 per frame)" in out
