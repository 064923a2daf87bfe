"""LeRobot data sets in: directories written here with pyarrow alone in LeRobot's layouts (v2.1: a
parquet file per episode; v3.0: episodes packed into files, indexed by meta/episodes/), imported
with a point-cloud column or with a depth column and a camera file, and the data sets refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from collectors.lerobot_format import import_lerobot, read_lerobot
from collectors.storage import DatasetError, DemoDataset
from d2a.cli import main

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

STEP_FEATURES = {key: {"dtype": "int64", "shape": [1], "names": None}
                 for key in ("frame_index", "episode_index", "index", "task_index")}
STEP_FEATURES["timestamp"] = {"dtype": "float32", "shape": [1], "names": None}
VIDEO = {"observation.images.top": {"dtype": "video", "shape": [96, 96, 3], "names": ["height", "width", "channel"]}}
TASK_WORDS = "put the block in the box"


def _arrow(values: np.ndarray):
    """A column as LeRobot's writer leaves it: scalars, fixed-size lists for vectors, nested lists beyond."""
    if values.ndim == 1:
        return pa.array(values)
    if values.ndim == 2:
        return pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()), values.shape[1])
    return pa.array(values.tolist(), type=pa.list_(pa.list_(pa.from_numpy_dtype(values.dtype))))


def write_lerobot(root, version, episodes, features):
    """``episodes`` (per episode: column -> (T, ...) values) in ``version``'s layout at ``root``; two
    episodes per chunk (v2.1) or per data file (v3.0), so that the templates' indices matter."""
    info = {"codebase_version": version, "robot_type": None, "fps": 10, "total_episodes": len(episodes),
            "total_frames": sum(len(e["action"]) for e in episodes), "total_tasks": 1, "chunks_size": 2,
            "features": {**STEP_FEATURES, **features}}
    tables, starts = [], np.cumsum([0] + [len(e["action"]) for e in episodes])
    for index, columns in enumerate(episodes):
        length = len(columns["action"])
        steps = {"episode_index": np.full(length, index), "frame_index": np.arange(length),
                 "index": starts[index] + np.arange(length), "timestamp": np.arange(length, dtype=np.float32) / 10,
                 "task_index": np.zeros(length, dtype=np.int64)}
        tables.append(pa.table({key: _arrow(values) for key, values in {**steps, **columns}.items()}))
    rows = [{"episode_index": index, "tasks": [TASK_WORDS], "length": len(steps["action"])}
            for index, steps in enumerate(episodes)]
    if version.startswith("v2"):
        info["data_path"] = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
        for index, table in enumerate(tables):
            file = root / f"data/chunk-{index // 2:03d}/episode_{index:06d}.parquet"
            file.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, file)
        (root / "meta").mkdir(parents=True)
        (root / "meta/episodes.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    else:
        info["data_path"] = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
        (root / "data/chunk-000").mkdir(parents=True)
        for file_index in range(0, len(tables), 2):
            pq.write_table(pa.concat_tables(tables[file_index : file_index + 2]),
                           root / f"data/chunk-000/file-{file_index // 2:03d}.parquet")
        for index, row in enumerate(rows):
            row |= {"data/chunk_index": 0, "data/file_index": index // 2,
                    "dataset_from_index": int(starts[index]), "dataset_to_index": int(starts[index + 1])}
        (root / "meta/episodes/chunk-000").mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist(rows[::-1]), root / "meta/episodes/chunk-000/file-000.parquet")
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))


def cloud_episodes(lengths=(3, 5, 4), outcomes=True):
    """Random steps with a (6, 6) cloud (xyz + rgb); the first and last episode succeed at their end."""
    rng = np.random.default_rng(0)
    episodes = []
    for index, length in enumerate(lengths):
        steps = {"observation.point_cloud": rng.normal(size=(length, 6, 6)).astype(np.float32),
                 "observation.state": rng.normal(size=(length, 9)).astype(np.float32),
                 "observation.environment_state": rng.normal(size=(length, 12)).astype(np.float32),
                 "action": rng.uniform(-1, 1, size=(length, 4)).astype(np.float32)}
        if outcomes:
            steps["next.reward"] = rng.uniform(size=length).astype(np.float32)
            steps["next.success"] = (np.arange(length) == length - 1) & (index != 1)
        episodes.append(steps)
    return episodes


def cloud_features(outcomes=True):
    features = {"observation.point_cloud": {"dtype": "float32", "shape": [6, 6]},
                "observation.state": {"dtype": "float32", "shape": [9]},
                "observation.environment_state": {"dtype": "float32", "shape": [12]},
                "action": {"dtype": "float32", "shape": [4]}, **VIDEO}
    if outcomes:
        features |= {"next.reward": {"dtype": "float32", "shape": [1]}, "next.success": {"dtype": "bool", "shape": [1]}}
    return features


@pytest.mark.parametrize("version, outcomes", [("v2.1", True), ("v3.0", False)])
def test_a_cloud_column_imports_row_by_row(tmp_path, version, outcomes):
    episodes = cloud_episodes(outcomes=outcomes)
    write_lerobot(tmp_path / "lerobot", version, episodes, cloud_features(outcomes))
    read = read_lerobot(tmp_path / "lerobot")
    assert read.tasks == [[TASK_WORDS]] * 3 and "observation.images.top" not in read.episodes[0]
    if outcomes:
        import_lerobot(tmp_path / "lerobot", tmp_path / "data", task="hammer",
                       full_state_key="observation.environment_state")
    else:
        main(["data", "import", "--lerobot", str(tmp_path / "lerobot"), "--task", "hammer", "--out",
              str(tmp_path / "data")])
    dataset = DemoDataset.open_for_training(tmp_path / "data")
    assert [(e.task, e.length) for e in dataset.metadata.episodes] == [("hammer", 3), ("hammer", 5), ("hammer", 4)]
    assert dataset.metadata.tasks == {"hammer": {"num_points": 6}}
    assert [(c.task, c.seed, c.kept) for c in dataset.metadata.collections] == [("hammer", -1, 3)]
    frames, row = dataset.frames(), 0
    for index, steps in enumerate(episodes):
        for step in range(len(steps["action"])):
            cloud = steps["observation.point_cloud"][step, :, :3]
            np.testing.assert_array_equal(frames["point_cloud"][row].numpy(), cloud)
            np.testing.assert_array_equal(frames["agent_pos"][row].numpy(), steps["observation.state"][step])
            full = steps["observation.environment_state" if outcomes else "observation.state"][step]
            np.testing.assert_array_equal(frames["state"][row].numpy(), full)
            np.testing.assert_array_equal(frames["action"][row].numpy(), steps["action"][step])
            assert float(frames["reward"][row]) == (float(steps["next.reward"][step]) if outcomes else 0.0)
            assert bool(frames["success"][row]) == (bool(steps["next.success"][step]) if outcomes else False)
            assert (int(frames["episode"][row]), int(frames["step"][row])) == (index, step)
            row += 1
    assert row == dataset.num_frames
    if outcomes:  # the episodes' outcomes are the file's; without them every episode was kept as a success
        assert [e.success for e in dataset.metadata.episodes] == [True, False, True]
        returns = [float(np.sum(steps["next.reward"], dtype=np.float32)) for steps in episodes]
        np.testing.assert_allclose([e.episode_return for e in dataset.metadata.episodes], returns, rtol=1e-6)
    else:
        assert all(e.success and e.episode_return == 0.0 for e in dataset.metadata.episodes)


FX, CX, CY, HEIGHT, WIDTH, CAMERA_Z = 10.0, 4.5, 3.5, 8, 10, 1.0
BOX = ((-0.1, -0.1, 0.3), (0.1, 0.1, 0.7))


def test_a_depth_column_fuses_into_the_back_projected_plane(tmp_path):
    """A camera 1 m above the base looking straight down sees a flat plane at a known depth d per step:
    pixel (u, v) lies at x = (u - cx) d / f, y = -(v - cy) d / f, z = 1 - d in the base frame."""
    plane = np.array([[0.50, 0.45], [0.52, 0.55]])  # metres, per episode and step
    rng = np.random.default_rng(1)
    episodes = [{"observation.depth": np.full((2, HEIGHT, WIDTH), 1.0) * np.round(d * 1000)[:, None, None],
                 "observation.state": rng.normal(size=(2, 4)).astype(np.float32),
                 "action": rng.normal(size=(2, 4)).astype(np.float32)} for d in plane]
    for steps in episodes:
        steps["observation.depth"] = steps["observation.depth"].astype(np.uint16)  # millimetres
    features = {"observation.depth": {"dtype": "uint16", "shape": [HEIGHT, WIDTH]},
                "observation.state": {"dtype": "float32", "shape": [4]},
                "action": {"dtype": "float32", "shape": [4]}, **VIDEO}
    write_lerobot(tmp_path / "lerobot", "v2.1", episodes, features)
    pose = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, CAMERA_Z], [0, 0, 0, 1]]  # OpenCV axes: z forward = down
    (tmp_path / "camera.json").write_text(json.dumps({"intrinsics": {"fx": FX, "fy": FX, "cx": CX, "cy": CY},
                                                      "pose": pose}))
    main(["data", "import", "--lerobot", str(tmp_path / "lerobot"), "--task", "reach", "--out", str(tmp_path / "data"),
          "--camera", str(tmp_path / "camera.json"), "--depth-scale", "0.001",
          "--crop-box=" + ",".join(map(str, BOX[0] + BOX[1])), "--num-points", "16"])
    dataset = DemoDataset.open_for_training(tmp_path / "data")
    assert dataset.metadata.tasks == {"reach": {"crop_box": [list(BOX[0]), list(BOX[1])], "num_points": 16}}
    clouds = dataset.frames()["point_cloud"].numpy().reshape(2, 2, 16, 3)
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    for index, depths in enumerate(plane):
        for step, depth in enumerate(depths):
            points = np.stack([(u - CX) * depth / FX, -(v - CY) * depth / FX, np.full(u.shape, CAMERA_Z - depth)], -1)
            points = points.reshape(-1, 3)
            inside = points[np.all((points >= BOX[0]) & (points <= BOX[1]), axis=1)]
            assert len(inside) == 16  # pixels u = 3..6, v = 2..5 at these depths: every one sampled once
            np.testing.assert_allclose(np.unique(clouds[index, step], axis=0), np.unique(inside, axis=0), atol=1e-6)
            np.testing.assert_allclose(clouds[index, step, :, 2], CAMERA_Z - depth, atol=1e-6)
    assert [e.min_points_in_crop for e in dataset.metadata.episodes] == [16, 16]
    with pytest.raises(DatasetError, match=r"depth \['observation.depth'\] needs a camera file"):
        import_lerobot(tmp_path / "lerobot", tmp_path / "other", task="reach")


@pytest.mark.parametrize("change, kwargs, message", [
    (lambda info: info["features"].pop("observation.point_cloud"), {},
     r"no point cloud .* not decoded here\. Its features: .*observation.images.top \(video \[96, 96, 3\]\)"),
    (lambda info: info.update(codebase_version="v1.6"), {}, r"codebase_version 'v1.6' is not read here"),
    (lambda info: None, {"cloud_key": "observation.images.top"}, r"stored as video frames, which are not decoded"),
    (lambda info: None, {"cloud_key": "observation.state"}, r"shape \[9\], not \(P, 3\) or \(P, 6\) points"),
])
def test_an_unusable_data_set_is_refused(tmp_path, change, kwargs, message):
    write_lerobot(tmp_path / "lerobot", "v3.0", cloud_episodes(lengths=(2, 2)), cloud_features())
    info = json.loads((tmp_path / "lerobot/meta/info.json").read_text())
    change(info)
    (tmp_path / "lerobot/meta/info.json").write_text(json.dumps(info))
    with pytest.raises(DatasetError, match=message):
        import_lerobot(tmp_path / "lerobot", tmp_path / "data", task="hammer", **kwargs)
    assert not (tmp_path / "data").exists()  # refused before anything is written
    with pytest.raises(DatasetError, match="not a LeRobot data set"):
        read_lerobot(tmp_path / "nothing")
