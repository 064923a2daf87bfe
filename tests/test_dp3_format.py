"""DP3 / MP1 zarr data sets in and out: against a zarr written here the way DP3's demo script
writes one, and a round trip through a data set collected here."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch

from collectors.dp3_format import export_dp3, import_dp3
from collectors.storage import DatasetError, DemoDataset
from d2a.cli import main

zarr = pytest.importorskip("zarr")


def write_dp3_like(path, lengths=(3, 5), points=6, with_full_state=True):
    """A zarr in DP3's layout, written with zarr directly: Blosc-compressed chunks of 100 rows,
    an rgb channel on the clouds, images, and cumulative episode ends."""
    import numcodecs

    rng = np.random.default_rng(0)
    steps = sum(lengths)
    arrays = {
        "point_cloud": rng.normal(size=(steps, points, 6)).astype(np.float32),
        "state": rng.normal(size=(steps, 9)).astype(np.float32),
        "full_state": rng.normal(size=(steps, 39)).astype(np.float32),
        "action": rng.uniform(-1, 1, size=(steps, 4)).astype(np.float32),
        "img": rng.integers(0, 255, size=(steps, 8, 8, 3)).astype(np.uint8),
    }
    if not with_full_state:
        del arrays["full_state"]
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    data = root.create_group("data")
    compressor = numcodecs.Blosc(cname="zstd", clevel=3, shuffle=1)
    for key, values in arrays.items():
        data.create_array(key, data=values, chunks=(100, *values.shape[1:]), compressor=compressor)
    root.create_group("meta").create_array("episode_ends", data=np.cumsum(lengths).astype(np.int64))
    return arrays


def test_import_reads_a_zarr_in_dp3s_layout(tmp_path):
    arrays = write_dp3_like(tmp_path / "hammer.zarr")
    dataset = import_dp3(tmp_path / "hammer.zarr", tmp_path / "data", task="hammer")
    assert [(e.task, e.length, e.success) for e in dataset.metadata.episodes] == [("hammer", 3, True),
                                                                                   ("hammer", 5, True)]
    assert dataset.metadata.tasks == {"hammer": {"num_points": 6}}
    frames = DemoDataset.open_for_training(tmp_path / "data").frames()
    np.testing.assert_array_equal(frames["point_cloud"].numpy(), arrays["point_cloud"][..., :3])
    np.testing.assert_array_equal(frames["agent_pos"].numpy(), arrays["state"])
    np.testing.assert_array_equal(frames["state"].numpy(), arrays["full_state"])
    np.testing.assert_array_equal(frames["action"].numpy(), arrays["action"])
    assert frames["episode"].tolist() == [0, 0, 0, 1, 1, 1, 1, 1]
    assert frames["step"].tolist() == [0, 1, 2, 0, 1, 2, 3, 4]
    assert not frames["success"].any()  # not stored in DP3's files
    # Without full_state, state repeats the proprioception; with given env options they are recorded.
    arrays = write_dp3_like(tmp_path / "lean.zarr", with_full_state=False)
    lean = import_dp3(tmp_path / "lean.zarr", tmp_path / "lean", task="hammer", env_kwargs={"num_points": 6,
                                                                                          "backend": "render"})
    np.testing.assert_array_equal(lean.frames()["state"].numpy(), arrays["state"])
    assert lean.metadata.tasks["hammer"] == {"num_points": 6, "backend": "render"}


@pytest.mark.parametrize("damage, message", [
    (lambda root: root["meta"].create_array("episode_ends", data=np.array([3, 9]), overwrite=True), "does not split"),
    (lambda root: root["meta"].create_array("episode_ends", data=np.array([5, 3, 8]), overwrite=True),
     "does not split"),
    (lambda root: root["data"].__delitem__("action"), "lacks"),
])
def test_import_refuses_an_inconsistent_file(tmp_path, damage, message):
    write_dp3_like(tmp_path / "bad.zarr")
    damage(zarr.open_group(str(tmp_path / "bad.zarr"), mode="a"))
    with pytest.raises(DatasetError, match=message):
        import_dp3(tmp_path / "bad.zarr", tmp_path / "data", task="hammer")
    with pytest.raises(DatasetError, match="not a DP3 zarr"):
        import_dp3(tmp_path / "nothing.zarr", tmp_path / "other", task="hammer")


def test_export_then_import_round_trips_a_collected_data_set(reach_data, tmp_path):
    main(["data", "export", reach_data, "--dp3", str(tmp_path / "reach.zarr")])
    original = DemoDataset.open(reach_data)
    root = zarr.open_group(str(tmp_path / "reach.zarr"), mode="r")  # read back with zarr alone
    lengths = [episode.length for episode in original.metadata.episodes]
    assert root["meta/episode_ends"][:].tolist() == np.cumsum(lengths).tolist()
    for key, source in (("point_cloud", "point_cloud"), ("state", "agent_pos"), ("full_state", "state"),
                        ("action", "action")):
        np.testing.assert_array_equal(root[f"data/{key}"][:], original.frames()[source].numpy().astype(np.float32))
    with pytest.raises(FileExistsError):
        export_dp3(reach_data, tmp_path / "reach.zarr")
    main(["data", "import", "--dp3", str(tmp_path / "reach.zarr"), "--out", str(tmp_path / "again"), "--task", "reach",
          "--image-size", "48", "--num-points", "128"])
    again = DemoDataset.open(tmp_path / "again")
    assert [episode.length for episode in again.metadata.episodes] == lengths
    for key in ("point_cloud", "agent_pos", "action"):
        assert torch.equal(again.frames()[key], original.frames()[key].float())
    # The collected set's env options come back with the given ones, so evaluation rebuilds its env.
    assert again.metadata.tasks["reach"] == {"image_size": 48, "num_points": 128}


def test_export_writes_clouds_that_training_refuses_for_their_older_box(reach_data, tmp_path):
    """A box check guards training, not the data: clouds cropped by an older box (points below
    Reach's table top) are refused for training and exported as they were collected."""
    copy = tmp_path / "reach"
    shutil.copytree(reach_data, copy)
    DemoDataset.open(copy).frames()["point_cloud"][0, :5, 2] = -0.02  # a memory map: on disk
    with pytest.raises(DatasetError, match="outside the box"):
        DemoDataset.open_for_training(copy)
    export_dp3(copy, tmp_path / "reach.zarr")
    exported = zarr.open_group(str(tmp_path / "reach.zarr"), mode="r")["data/point_cloud"]
    np.testing.assert_array_equal(exported[0, :5, 2], np.full(5, -0.02, dtype=np.float32))


def test_a_policy_trains_on_an_imported_data_set(tmp_path):
    from d2a_agents.policy.agent import PolicyConfig
    from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
    from d2a_agents.policy.train import TrainPolicyConfig, train_policy

    write_dp3_like(tmp_path / "reach.zarr", lengths=(12, 10))
    import_dp3(tmp_path / "reach.zarr", tmp_path / "data", task="reach")
    policy = PolicyConfig(algo="mp1", num_points=4, encoder=EncoderConfig(point_widths=(8,)),
                          network=VelocityNetConfig(hidden=16, layers=1))
    config = TrainPolicyConfig(data=str(tmp_path / "data"), out=str(tmp_path / "run"), policy=policy, steps=2,
                               batch_size=4, eval_episodes=0, progress=False)
    trained, history = train_policy(dataclasses.replace(config, augment_shift=0.0))
    assert history == [] and trained.normalizers["agent_pos"].low.shape == (9,)
