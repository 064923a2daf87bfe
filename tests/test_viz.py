"""``d2a viz pointcloud`` and ``d2a viz imagine`` on real MuJoCo scenes, at tiny sizes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import d2a_agents.world_model.viz as imagination_viz
from d2a.cli import main
from tests.test_imagination import ENV_KWARGS, write_world_model
from tests.test_reward import brute_force_chamfer

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def test_viz_pointcloud_writes_a_png(tmp_path: Path) -> None:
    out = tmp_path / "cloud.png"
    main(["viz", "pointcloud", "--task", "hammer", "--out", str(out), "--steps", "2",
          "--num-points", str(ENV_KWARGS["num_points"]), "--image-size", str(ENV_KWARGS["image_size"])])
    assert out.read_bytes().startswith(PNG_SIGNATURE)


def test_viz_imagine_draws_the_true_future_and_its_distances(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    checkpoint = write_world_model(tmp_path / "wm.pt")  # horizon 2
    drawn: list[dict] = []
    real_plot = imagination_viz.plot_imagination

    def recording_plot(frames, horizon, title, out, box):
        drawn.extend(frames)
        assert horizon == 2
        return real_plot(frames, horizon, title, out, box)

    monkeypatch.setattr(imagination_viz, "plot_imagination", recording_plot)
    out = tmp_path / "imagine.png"
    path = imagination_viz.plot_task_imagination(checkpoint, "hammer", out, seed=0, steps=(1, 3), **ENV_KWARGS)
    assert path == out and out.read_bytes().startswith(PNG_SIGNATURE)
    assert [frame["step"] for frame in drawn] == [1, 3]
    first, later = drawn
    np.testing.assert_array_equal(first["future"], later["current"])  # t + H of step 1 is step 3's present
    for frame in drawn:
        assert frame["imagined"].shape == frame["current"].shape
        for error, reference in (("imagined_error", "imagined"), ("persistence_error", "current")):
            assert frame[error] == pytest.approx(brute_force_chamfer(frame[reference], frame["future"]), abs=1e-6)
