"""Fault injection: damaged data sets, concurrent writers and bad input get a clear one-line
error, a non-zero exit and leave every file as it was.

Each case runs the real command line (``d2a.cli.main``) where the guarantee is the CLI's, and
compares the data set's bytes before and after.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from collectors.atomic import LOCK_NAME, DirectoryBusyError, exclusive_writer, is_lock_file
from collectors.storage import BUFFER_DIR, METADATA_FILE, DatasetError, DemoDataset
from d2a.cli import main
from tests.conftest import SMALL_ENV_KWARGS

STORAGE = Path(BUFFER_DIR) / "storage"


def fingerprint(directory: Path) -> dict[str, str]:
    """Hash of every file but the writer lock: equal fingerprints, unaltered data set."""
    return {
        str(path.relative_to(directory)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(directory.rglob("*")) if path.is_file() and path.name != LOCK_NAME
    }


def fails_with(argv: list[str], capsys, *fragments: str) -> str:
    """Run the CLI, expect a non-zero exit whose one-line message holds every fragment."""
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    message = str(stopped.value.code)
    assert stopped.value.code not in (0, None), "the command should have failed"
    assert message.startswith("d2a: error: ") and "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, message
    return message


@pytest.fixture
def damaged(reach_data, tmp_path) -> Path:
    """A private copy of the shared data set, free to damage."""
    copy = tmp_path / "reach"
    shutil.copytree(reach_data, copy)
    return copy


def test_truncated_memmap_is_refused_by_a_read_only_command_without_writing(damaged, capsys):
    cloud = damaged / STORAGE / "point_cloud.memmap"
    with open(cloud, "r+b") as handle:
        handle.truncate(cloud.stat().st_size // 2)
    before = fingerprint(damaged)
    fails_with(["data", "info", str(damaged)], capsys, "point_cloud.memmap", "damaged")
    assert fingerprint(damaged) == before  # data info did not re-grow the file


@pytest.mark.parametrize("victim", ["action.memmap", "meta.json"])
def test_missing_buffer_file_is_named(damaged, capsys, victim):
    (damaged / STORAGE / victim).unlink()
    fails_with(["data", "info", str(damaged)], capsys, victim)


def test_missing_metadata_is_a_clear_error(damaged, capsys):
    (damaged / METADATA_FILE).unlink()
    fails_with(["data", "info", str(damaged)], capsys, METADATA_FILE, "missing")


def test_non_finite_clouds_are_refused_before_training(damaged, capsys, tmp_path):
    dataset = DemoDataset.open(damaged)
    dataset.frames()["point_cloud"][250, 3, 1] = float("nan")  # episode 1, step 50 (a memory map: on disk)
    before = fingerprint(damaged)
    for command in (["train-policy", "--algo", "mp1"], ["train-wm"]):
        fails_with([*command, "--data", str(damaged), "--out", str(tmp_path / command[0] / "run")], capsys,
                   "point_cloud", "non-finite", "episode 1, step 50")
        written = [p for p in (tmp_path / command[0]).rglob("*") if p.is_file()]
        assert all(is_lock_file(p) for p in written), written  # nothing trained, nothing saved
    assert fingerprint(damaged) == before



def test_clouds_from_another_box_are_refused_before_training(damaged, capsys, tmp_path):
    """Points below Reach's table top are what a box with a lower floor (an older default) kept."""
    DemoDataset.open(damaged).frames()["point_cloud"][0, :5, 2] = -0.02  # episode 0's first frame
    for command in (["train-policy", "--algo", "mp1"], ["train-wm"]):
        fails_with([*command, "--data", str(damaged), "--out", str(tmp_path / command[0] / "run")], capsys,
                   "5 points of reach", "outside the box", "collect them again")
    metadata = json.loads((damaged / METADATA_FILE).read_text())
    metadata["tasks"]["reach"]["crop_box"] = [[-0.6, 0.25, -0.05], [0.6, 0.97, 0.7]]  # the box they came from
    (damaged / METADATA_FILE).write_text(json.dumps(metadata))
    DemoDataset.open_for_training(damaged)
    metadata["tasks"]["reach"].pop("crop_box")
    for collection in metadata["collections"]:
        collection["seed"] = -1  # imported: their box is the source's, not checked
    (damaged / METADATA_FILE).write_text(json.dumps(metadata))
    DemoDataset.open_for_training(damaged)

def test_a_data_set_without_episodes_is_refused_for_training(tmp_path):
    empty = DemoDataset.create(tmp_path / "empty", capacity=10)
    with pytest.raises(DatasetError, match="no episodes"):
        DemoDataset.open_for_training(empty.directory)


def test_a_second_writer_is_refused_and_the_first_keeps_its_data(damaged, capsys):
    before = fingerprint(damaged)
    argv = ["collect", "--task", "reach", "--episodes", "3", "--append", "--out", str(damaged),
            "--image-size", str(SMALL_ENV_KWARGS["image_size"]), "--num-points", str(SMALL_ENV_KWARGS["num_points"])]
    with exclusive_writer(damaged):  # another collection is writing
        fails_with(argv, capsys, "another process is writing to", str(damaged))
        with pytest.raises(DirectoryBusyError):
            with exclusive_writer(damaged):
                pass
    assert fingerprint(damaged) == before


def test_overwrite_keeps_the_lock_and_an_interrupted_output_can_be_reused(tmp_path):
    out = tmp_path / "fresh"
    with exclusive_writer(out):
        pass  # a collection refused after taking the lock leaves only the lock file behind
    assert [p.name for p in out.iterdir()] == [LOCK_NAME]
    dataset = DemoDataset.create(out, capacity=10)  # not refused as "already holds files"
    assert dataset.num_frames == 0
    overwritten = DemoDataset.create(out, capacity=10, overwrite=True)
    assert (out / LOCK_NAME).exists() and overwritten.num_frames == 0


def test_wrong_length_memmap_with_right_size_metadata_is_caught(damaged, capsys):
    """A memmap replaced by one of another shape (same key, other bytes) is refused too."""
    action = damaged / STORAGE / "action.memmap"
    np.zeros(7, dtype=np.float32).tofile(action)
    fails_with(["data", "info", str(damaged)], capsys, "action.memmap", "bytes")


@pytest.mark.parametrize("command", [["train-policy", "--algo", "mp1"], ["train-wm"]])
def test_a_second_trainer_into_the_same_output_is_refused(reach_data, tmp_path, capsys, command):
    out = tmp_path / "run" / ("wm.pt" if command[0] == "train-wm" else "")
    lock_dir, lock_name = (out.parent, f".{out.name}.lock") if command[0] == "train-wm" else (out, LOCK_NAME)
    with exclusive_writer(lock_dir, lock_name):  # another trainer is running
        fails_with([*command, "--data", reach_data, "--out", str(out), "--steps", "1"], capsys,
                   "another process is writing to")


def test_an_output_that_cannot_be_written_is_refused_before_training(reach_data, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    fails_with(["train-policy", "--algo", "mp1", "--data", reach_data, "--out", str(blocker / "run"),
                "--steps", "1"], capsys, "cannot write to")
    assert blocker.read_text() == "not a directory"


def test_a_world_model_batch_larger_than_the_data_is_refused(reach_data, tmp_path, capsys):
    fails_with(["train-wm", "--data", reach_data, "--out", str(tmp_path / "wm.pt"), "--batch-size", "100000",
                "--resolution", "16", "16", "8"], capsys, "batch size 100000 exceeds")
    assert not (tmp_path / "wm.pt").exists()


def test_an_append_whose_seeds_overlap_a_stored_collection_is_refused(damaged, capsys):
    """The stored collection used seeds 0..1; a run from seed 1 (or from 0 backwards) would repeat them."""
    before = fingerprint(damaged)
    common = ["collect", "--task", "reach", "--episodes", "2", "--append", "--out", str(damaged),
              "--image-size", str(SMALL_ENV_KWARGS["image_size"]), "--num-points", str(SMALL_ENV_KWARGS["num_points"])]
    fails_with([*common, "--seed", "1"], capsys, "overlap seeds 0..1")
    assert fingerprint(damaged) == before


def test_a_diverging_policy_run_stops_and_keeps_its_last_finite_checkpoint(reach_data, tmp_path, monkeypatch):
    import d2a_agents.policy.train as trainer
    from d2a_agents.checkpoint import load_checkpoint
    from d2a_agents.policy.agent import PolicyConfig
    from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig

    real_step, calls = trainer.training_step, []

    def diverging_step(*args, **kwargs):
        calls.append(1)
        info = real_step(*args, **kwargs)
        return {**info, "mse": float("nan")} if len(calls) == 3 else info

    monkeypatch.setattr(trainer, "training_step", diverging_step)
    out = tmp_path / "run"
    tiny = PolicyConfig(algo="mp1", num_points=16, encoder=EncoderConfig(point_widths=(8,)),
                        network=VelocityNetConfig(hidden=16, layers=1))
    config = trainer.TrainPolicyConfig(data=reach_data, out=str(out), policy=tiny, steps=6, batch_size=4,
                                       eval_episodes=0, checkpoint_every=2, progress=False)
    with pytest.raises(FloatingPointError, match="loss became nan at step 3.*keeps the last finite checkpoint"):
        trainer.train_policy(config)
    payload = load_checkpoint(out / "policy.pt", "policy")
    assert payload["step"] == 2
    assert all(torch.isfinite(value).all() for value in payload["model"].values() if value.is_floating_point())


KILLED_RUNS = {  # command, checkpoint inside the output, checkpoint kind, weights compared, total steps
    "policy": (["train-policy", "--algo", "mp1", "--steps", "400", "--batch-size", "8", "--policy-points", "16",
                "--eval-episodes", "0"], "policy.pt", "policy", ("model", "ema"), 400),
    "world model": (["train-wm", "--steps", "200", "--batch-size", "2", "--queries", "256", "--validate-every", "200",
                     "--resolution", "16", "16", "8"], "wm.pt", "world_model", ("model",), 200),
}


@pytest.mark.parametrize("trainer", sorted(KILLED_RUNS))
def test_a_killed_training_resumes_to_the_uninterrupted_result(reach_data, tmp_path, trainer):
    """kill -9 after the first checkpoint, rerun the same command: the final weights are those
    of a run that was never interrupted (generator, optimizer, scheduler and EMA all resume)."""
    import signal
    import subprocess
    import sys
    import time

    from d2a_agents.checkpoint import load_checkpoint

    arguments, file, kind, weights, steps = KILLED_RUNS[trainer]

    def command(out: Path) -> list[str]:
        out = out / file if kind == "world_model" else out
        return [sys.executable, "-m", "d2a.cli", *arguments, "--data", reach_data, "--out", str(out), "--threads", "1"]

    killed = tmp_path / "killed"
    process = subprocess.Popen(command(killed), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and not (killed / file).exists() and process.poll() is None:
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    interrupted_at = load_checkpoint(killed / file, kind)["step"]
    assert 0 < interrupted_at < steps, "the kill should land between the first checkpoint and the end"
    subprocess.run(command(killed), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    subprocess.run(command(tmp_path / "straight"), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    resumed = load_checkpoint(killed / file, kind)
    straight = load_checkpoint(tmp_path / "straight" / file, kind)
    assert resumed["step"] == straight["step"] == steps
    for key in weights:
        for name, value in straight[key].items():
            assert torch.equal(resumed[key][name], value), f"{key}.{name}"
