"""The command line builds the configurations its help promises (no training runs here)."""

from __future__ import annotations

import dataclasses

import pytest

import benchmarks.success
import benchmarks.world_model
import d2a.demo
import d2a_agents.policy.train
import d2a_agents.world_model.train
from d2a.cli import main


@pytest.fixture
def captured(monkeypatch) -> dict[str, object]:
    """The configuration the last command passed on, instead of running it."""
    seen: dict[str, object] = {}

    def train_policy(config):
        seen["config"] = config
        return None, []

    def run(config):
        seen["config"] = config

    monkeypatch.setattr(d2a_agents.policy.train, "train_policy", train_policy)
    monkeypatch.setattr(d2a_agents.world_model.train, "train_world_model", train_policy)
    monkeypatch.setattr(benchmarks.success, "run", run)
    monkeypatch.setattr(benchmarks.world_model, "run", run)
    monkeypatch.setattr(d2a.demo, "run_demo", run)
    return seen


class CollectStopped(Exception):
    """Raised by the stand-in for ``collect`` (the command would go on to read the data set)."""


@pytest.fixture
def collect_config(captured, monkeypatch) -> dict[str, object]:
    """``captured``, and ``d2a collect`` records its configuration, then raises CollectStopped."""
    import collectors.collect

    def collect(config):
        captured["config"] = config
        raise CollectStopped

    monkeypatch.setattr(collectors.collect, "collect", collect)
    return captured


def test_train_policy_defaults_to_the_cpu_preset_and_flags_override_it(captured):
    main(["train-policy", "--data", "d", "--out", "o", "--algo", "mp1", "--steps", "7"])
    config = captured["config"]
    assert (config.steps, config.batch_size, config.learning_rate) == (7, 256, 1e-3)
    assert (config.policy.algo, config.policy.num_points, config.policy.network.hidden) == ("mp1", 64, 128)
    assert not config.policy.encoder.use_imagination  # the algo decides, whatever the preset said
    assert (config.device, config.threads, config.holdout_episodes) == ("cpu", 0, 0)
    assert config.trim_after_success == 10
    main(["train-policy", "--data", "d", "--out", "o", "--trim-after-success", "-1"])
    assert captured["config"].trim_after_success == -1
    assert captured["config"].policy.meanflow_output == "velocity"
    main(["train-policy", "--data", "d", "--out", "o", "--meanflow-output", "action"])
    assert captured["config"].policy.meanflow_output == "action"
    main(["train-policy", "--data", "d", "--out", "o", "--algo", "dp"])
    assert (captured["config"].batch_size, captured["config"].learning_rate) == (64, 1e-4)  # the image preset's
    main(["train-policy", "--data", "d", "--out", "o", "--algo", "dp", "--lr", "3e-4", "--batch-size", "16"])
    assert (captured["config"].batch_size, captured["config"].learning_rate) == (16, 3e-4)
    main(["train-policy", "--data", "d", "--out", "o", "--preset", "paper"])
    assert captured["config"].trim_after_success == -1  # the paper trains on every frame
    assert captured["config"].augment_shift == 0.0  # the paper's preset moves nothing
    main(["train-policy", "--data", "d", "--out", "o"])
    assert captured["config"].augment_shift is None  # the cpu preset's: 2 cm on Meta-World
    main(["train-policy", "--data", "d", "--out", "o", "--augment-shift", "0.02"])
    assert captured["config"].augment_shift == 0.02
    for bad in ("-0.01", "inf", "nan"):
        with pytest.raises(SystemExit):
            main(["train-policy", "--data", "d", "--out", "o", "--augment-shift", bad])


def test_train_policy_state_reference_device_threads_and_holdout(captured):
    main(["train-policy", "--data", "d", "--out", "o", "--algo", "mp1-state", "--device", "cuda", "--threads", "1",
          "--holdout-episodes", "2", "--adaptive-power", "0.5", "--cfg-guidance", "amplify", "--cfg-scale", "2"])
    config = captured["config"]
    assert (config.device, config.threads, config.holdout_episodes) == ("cuda", 1, 2)
    assert config.policy.adaptive_power == 0.5
    assert (config.policy.cfg_guidance, config.policy.cfg_scale) == ("amplify", 2.0)
    assert not config.policy.encoder.use_cloud and config.policy.encoder.state_key == "state"


def test_train_wm_device_and_threads(captured):
    main(["train-wm", "--data", "d", "--out", "o.pt", "--device", "cuda", "--threads", "2"])
    assert (captured["config"].device, captured["config"].threads) == ("cuda", 2)
    main(["train-wm", "--data", "d", "--out", "o.pt"])
    assert (captured["config"].device, captured["config"].threads) == ("cpu", 0)


def test_bench_wm_sets_the_main_model_the_baseline_row_and_the_collection(captured):
    main(["bench", "wm", "--task", "push", "--horizon", "1", "--horizon", "8", "--steps", "9", "--backend", "render"])
    config = captured["config"]
    assert config.tasks == ("push",) and config.horizons == (1, 8)
    main_model, baseline = config.models
    assert (main_model.model.resolution, main_model.model.encoder, main_model.steps) == ((128, 128, 32),
                                                                                         "point-scatter", 9)
    assert (baseline.model.resolution, baseline.model.encoder, baseline.steps) == ((32, 32, 8), "volume-conv", 300)
    assert config.env_kwargs == {"num_points": 4096, "image_size": 256, "backend": "render"}
    main(["bench", "wm", "--baseline-steps", "0", "--resolution", "64", "64", "16", "--encoder", "volume-conv",
          "--mode", "volume", "--num-points", "1024"])
    config = captured["config"]
    assert [model.label for model in config.models] == ["64x64x16 volume-conv volume"]
    assert config.env_kwargs == {"num_points": 1024, "image_size": 256}


def test_the_cli_offers_every_policy_variant_and_expert_kind():
    from collectors.adroit_experts import EXPERT_KINDS
    from d2a.cli_options import ALGOS, STATE_ALGOS
    from d2a.cli_options import EXPERT_KINDS as CLI_EXPERT_KINDS
    from d2a_agents.policy.agent import ALGORITHMS, STATE_ALGORITHMS

    assert ALGOS == ALGORITHMS and CLI_EXPERT_KINDS == EXPERT_KINDS
    assert STATE_ALGOS == STATE_ALGORITHMS == ("mp1-state", "dp3-state")


def test_the_learnability_check_takes_its_state_policy(monkeypatch):
    import benchmarks.experts

    seen = {}
    monkeypatch.setattr(benchmarks.experts, "run", lambda given: seen.setdefault("config", given))
    main(["bench", "experts", "--imitation-demos", "10", "--imitation-algo", "dp3-state"])
    assert (seen["config"].imitation_algo, seen["config"].imitation_demos) == ("dp3-state", 10)
    with pytest.raises(SystemExit):
        main(["bench", "experts", "--imitation-algo", "mp1"])  # reads clouds: not a state reference


def test_dagger_takes_the_checks_options_and_its_rounds(monkeypatch):
    import benchmarks.dagger

    seen = {}
    monkeypatch.setattr(benchmarks.dagger, "run", lambda given: seen.setdefault("config", given))
    main(["bench", "dagger", "--task", "adroit-hammer", "--rounds", "2", "--episodes-per-round", "5",
          "--imitation-demos", "20", "--imitation-dart-noise", "0.1", "--expert", "planner", "--workdir", "w"])
    config = seen["config"]
    assert (config.rounds, config.episodes_per_round) == (2, 5)
    assert config.check.tasks == ("adroit-hammer",) and config.check.imitation_demos == 20
    assert (config.check.imitation_dart_noise, config.check.expert, config.check.workdir) == (0.1, "planner", "w")


def test_the_cli_offers_every_kind_of_evaluation_layouts(captured):
    from d2a.cli_options import EVAL_LAYOUTS
    from d2a_agents.policy.train import EVAL_LAYOUTS as TRAINER_LAYOUTS

    assert EVAL_LAYOUTS == TRAINER_LAYOUTS
    main(["train-policy", "--data", "d", "--out", "o", "--eval-layouts", "fresh"])
    assert captured["config"].eval_layouts == "fresh"
    main(["bench", "success", "--eval-layouts", "fresh"])
    assert captured["config"].eval_layouts == "fresh"


def test_train_policy_paper_preset(captured):
    main(["train-policy", "--data", "d", "--out", "o", "--preset", "paper", "--policy-points", "512"])
    config = captured["config"]
    assert (config.steps, config.batch_size, config.learning_rate) == (47_000, 128, 1e-4)
    assert (config.policy.algo, config.policy.num_points, config.policy.encoder.point_widths) == ("d2a", 512,
                                                                                                  (64, 128, 256))


def test_bench_success_options(captured):
    main(["bench", "success", "--task", "push", "--algo", "mp1", "--algo", "dp3", "--seed", "1", "--steps", "9"])
    config = captured["config"]
    assert (config.tasks, config.algos, config.seeds, config.policy.steps) == (("push",), ("mp1", "dp3"), (1,), 9)
    assert config.policy.batch_size == 256 and config.evaluations == 5 and config.final_episodes == 100
    assert config.env_kwargs == {} and config.world_model.resolution == (32, 32, 8)
    main(["bench", "success", "--image-size", "256", "--num-points", "4096", "--backend", "render",
          "--world-model", "cpu", "--wm-steps", "1500"])
    dense = captured["config"]
    assert dense.env_kwargs == {"image_size": 256, "num_points": 4096, "backend": "render"}
    assert (dense.world_model.resolution, dense.world_model.encoder, dense.world_model_steps) == (
        (128, 128, 32), "point-scatter", 1500)
    main(["bench", "success", "--preset", "paper"])
    paper = captured["config"]
    assert paper.seeds == (0, 1, 2) and paper.evaluations == 15 and paper.final_episodes == 100
    assert paper.eval_layouts == "fresh" and dense.eval_layouts == "fixed"


def test_demo_options_change_only_what_they_name(captured):
    main(["demo", "--task", "push", "--policy-steps", "5"])
    config = captured["config"]
    assert (config.task, config.policy.steps, config.policy.batch_size, config.episodes) == ("push", 5, 256, 10)
    assert config.policy.policy == d2a.demo.DemoConfig().policy.policy


def test_eval_passes_how_to_act_to_a_checkpoint_only(monkeypatch):
    import d2a_agents.policy.checkpoints
    from d2a_agents.policy.checkpoints import Acting

    seen = {}

    class Result:
        def summary(self) -> str:
            return ""

    def evaluate_checkpoint(path, task, episodes, seed, **options):
        seen.update(options, path=path)
        return Result()

    monkeypatch.setattr(d2a_agents.policy.checkpoints, "evaluate_checkpoint", evaluate_checkpoint)
    main(["eval", "--policy", "runs/p", "--task", "push", "--n-action-steps", "1", "--action-draws", "8",
          "--sample-steps", "4"])
    assert (seen["path"], seen["acting"]) == ("runs/p", Acting(n_action_steps=1, action_draws=8, sample_steps=4))
    main(["eval", "--policy", "runs/p", "--task", "push"])
    assert seen["acting"] == Acting()  # the checkpoint's own chunking, one draw
    for option in ("--n-action-steps", "--action-draws", "--sample-steps"):
        with pytest.raises(SystemExit, match="expert acts step by step"):
            main(["eval", "--policy", "expert", option, "2"])
    with pytest.raises(SystemExit, match="applies to --policy expert"):
        main(["eval", "--policy", "runs/p", "--task", "push", "--expert", "planner"])


def test_abbreviated_options_are_refused(captured, capsys):
    main(["demo", "--out", "runs/demo"])
    assert captured["config"].out == "runs/demo"
    with pytest.raises(SystemExit):
        main(["train-policy", "--data", "d", "--out", "o", "--eval-ev", "5"])  # --eval-every, abbreviated
    assert "unrecognized arguments: --eval-ev" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["eval", "--policy", "p.pt", "--seed", "-1"], "argument --seed: must be at least 0, got -1"),
    (["eval", "--policy", "p.pt", "--n-action-steps", "0"], "argument --n-action-steps: must be at least 1"),
    (["eval", "--policy", "p.pt", "--action-draws", "0"], "argument --action-draws: must be at least 1"),
    (["act", "--policy", "p.pt", "--action-draws", "0"], "argument --action-draws: must be at least 1"),
    (["eval", "--policy", "p.pt", "--sample-steps", "0"], "argument --sample-steps: must be at least 1"),
    (["bench", "envs", "--steps", "0"], "argument --steps: must be at least 1, got 0"),
    (["train-wm", "--data", "d", "--out", "o", "--batch-size", "0"], "argument --batch-size: must be at least 1"),
    (["train-policy", "--data", "d", "--out", "o", "--policy-points", "0"],
     "argument --policy-points: must be at least 1"),
    (["collect", "--task", "reach", "--out", "o", "--seed", "1.5"], "argument --seed: invalid integer value: '1.5'"),
])
def test_integer_flags_are_checked_before_any_work(captured, capsys, argv, message):
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2 and message in capsys.readouterr().err
    assert "config" not in captured  # the command never ran


def test_defaults_live_in_the_configs_alone(collect_config):
    """With only the required options, each command builds exactly its config's defaults."""
    from collectors.collect import CollectConfig
    from d2a_agents.policy.train import POLICY_PRESETS, TrainPolicyConfig
    from d2a_agents.world_model.train import TrainWorldModelConfig

    main(["train-wm", "--data", "d", "--out", "o.pt"])
    assert collect_config["config"] == TrainWorldModelConfig(data="d", out="o.pt")
    main(["train-policy", "--data", "d", "--out", "o"])
    assert collect_config["config"] == TrainPolicyConfig.from_preset(POLICY_PRESETS["cpu"], data="d", out="o")
    with pytest.raises(CollectStopped):
        main(["collect", "--task", "reach", "--out", "o"])
    assert collect_config["config"] == CollectConfig(tasks=("reach",), out="o")


@pytest.mark.parametrize("argv, module, config", [
    (["bench", "envs"], "benchmarks.envs", "EnvBenchConfig"),
    (["bench", "experts"], "benchmarks.experts", "ExpertBenchConfig"),
    (["bench", "latency"], "benchmarks.latency", "LatencyBenchConfig"),
    (["bench", "eval", "--policy", "p", "--task", "push"], "benchmarks.evaluation_speed", "EvaluationSpeedConfig"),
    (["bench", "train"], "benchmarks.train", "TrainBenchConfig"),
    (["bench", "ablate", "--data", "d", "--task", "hammer"], "benchmarks.ablation", "AblationConfig"),
    (["bench", "ray"], "benchmarks.ray_scaling", "RayScalingConfig"),
    (["bench", "dagger"], "benchmarks.dagger", "DaggerConfig"),
    (["bench", "wm-fit", "--world-model", "w", "--data", "d", "--demos", "5"], "benchmarks.world_model_fit",
     "WorldModelFitConfig"),
    (["bench", "policy-fit", "--policy", "p", "--policy", "q"], "benchmarks.policy_fit", "PolicyFitConfig"),
])
def test_bench_defaults_live_in_their_configs(argv, module, config, monkeypatch):
    import importlib

    bench = importlib.import_module(module)
    seen = {}
    monkeypatch.setattr(bench, "run", lambda given: seen.setdefault("config", given))
    main(argv)
    required = {"AblationConfig": {"data": "d", "task": "hammer"},
                "EvaluationSpeedConfig": {"policy": "p", "task": "push"},
                "WorldModelFitConfig": {"world_model": "w", "data": "d", "demos": 5},
                "PolicyFitConfig": {"policies": ("p", "q")}}.get(config, {})
    assert seen["config"] == getattr(bench, config)(**required)


def test_bench_success_bench_wm_and_demo_defaults_live_in_their_configs(captured):
    main(["bench", "success"])
    assert captured["config"] == benchmarks.success.PRESETS["cpu"]
    main(["bench", "wm"])
    assert captured["config"] == benchmarks.world_model.WorldModelBenchConfig()
    main(["demo"])
    assert captured["config"] == d2a.demo.DemoConfig()


def test_ray_option_takes_an_optional_address(collect_config):
    for flags, address in (([], None), (["--ray"], "local"), (["--ray", "auto"], "auto")):
        with pytest.raises(CollectStopped):
            main(["collect", "--task", "reach", "--out", "o", *flags])
        assert collect_config["config"].ray_address == address
    main(["bench", "success", "--ray", "ray://head:10001", "--threads", "2"])
    assert (collect_config["config"].ray_address, collect_config["config"].threads) == ("ray://head:10001", 2)


def test_demos_reach_the_trainers_and_the_bench(captured):
    main(["train-policy", "--data", "d", "--out", "o", "--demos", "5"])
    assert captured["config"].demos == 5
    main(["train-wm", "--data", "d", "--out", "o.pt", "--demos", "2"])
    assert captured["config"].demos == 2
    main(["bench", "success", "--demos", "1", "--pool", "20", "--cells", "kept/cells"])
    assert (captured["config"].demos, captured["config"].pool, captured["config"].cells) == (1, 20, "kept/cells")
    main(["train-policy", "--data", "d", "--out", "o"])
    assert captured["config"].demos is None  # every episode
    main(["train-policy", "--data", "d", "--out", "o", "--imagined-points", "256", "--oracle-horizon", "12"])
    assert (captured["config"].policy.imagined_points, captured["config"].policy.oracle_horizon) == (256, 12)
    main(["bench", "success", "--wm-rollouts", "20", "--rollout-noise", "0.5"])
    assert (captured["config"].wm_rollouts, captured["config"].rollout_noise) == (20, 0.5)
    main(["bench", "success", "--wm-without-actions"])
    preset_world_model = benchmarks.success.PRESETS["cpu"].world_model
    assert captured["config"].world_model == dataclasses.replace(preset_world_model, reads_actions=False)
    main(["bench", "success", "--world-model", "demo", "--wm-without-actions"])
    assert captured["config"].world_model.resolution == (32, 32, 8) and not captured["config"].world_model.reads_actions
    main(["bench", "success", "--imagined-points", "256"])
    assert captured["config"].policy.policy.imagined_points == 256 and captured["config"].policy.policy.num_points == 64
    main(["bench", "success", "--policy-points", "128", "--steps", "300", "--oracle-horizon", "8"])
    policy = captured["config"].policy
    assert (policy.steps, policy.policy.num_points, policy.policy.imagined_points) == (300, 128, None)
    assert policy.policy.oracle_horizon == 8
    main(["bench", "success", "--stacked-horizon", "1", "--stacked-horizon", "2"])
    assert captured["config"].policy.policy.stacked_horizons == (1, 2)
    name = benchmarks.success._cell_name(captured["config"], "push", "d2a-oracle", 0)
    assert name.endswith("_stacked_horizons1,2")  # its cells apart from the single horizon's
    main(["train-policy", "--data", "d", "--out", "o", "--stacked-horizon", "2"])
    assert captured["config"].policy.stacked_horizons == (2,)
    main(["bench", "success", "--meanflow-output", "action"])
    assert captured["config"].policy.policy.meanflow_output == "action"
    name = benchmarks.success._cell_name(captured["config"], "push", "mp1", 0)
    assert name.endswith("_meanflow_outputaction")  # its cells apart from the rest


def test_bench_table1_options_and_defaults(monkeypatch):
    import benchmarks.table1

    seen = {}
    monkeypatch.setattr(benchmarks.table1, "run", lambda config, report_only: seen.update(config=config,
                                                                                           report=report_only))
    main(["bench", "table1"])
    assert seen == {"config": benchmarks.table1.Table1Config(), "report": False}
    main(["bench", "table1", "--group", "hard", "--algo", "d2a", "--seed", "2", "--evaluations", "15",
          "--workdir", "w", "--results", "r", "--report"])
    config = seen["config"]
    assert (config.groups, config.algos, config.seeds, config.results) == (("hard",), ("d2a",), (2,), "r")
    assert (config.bench.evaluations, config.bench.workdir, seen["report"]) == (15, "w", True)
    assert config.cell_config().env_kwargs == {"num_points": 4096, "image_size": 256, "backend": "render"}
    default = benchmarks.table1.Table1Config().cell_config()
    assert config.bench.policy == default.policy  # the cpu preset: cells keep their short names
    main(["bench", "table1", "--policy-points", "128"])
    budget = seen["config"].cell_config()
    assert (budget.policy.policy.num_points, budget.policy.steps) == (128, default.policy.steps)
    cell_path = benchmarks.success.cell_path
    assert cell_path(budget, "push", "mp1", 0) != cell_path(default, "push", "mp1", 0)


def test_bench_envs_runs_the_render_thread_comparison_alone_when_asked(monkeypatch):
    import benchmarks.envs

    seen = {}
    monkeypatch.setattr(benchmarks.envs, "run", lambda config: seen.setdefault("run", config))
    monkeypatch.setattr(benchmarks.envs, "render_thread_comparison", lambda config: seen.setdefault("threads", config))
    main(["bench", "envs", "--render-threads", "--render-rounds", "2", "--task", "push"])
    assert list(seen) == ["threads"] and (seen["threads"].render_rounds, seen["threads"].task) == (2, "push")
    main(["bench", "envs"])
    assert seen["run"].render_rounds == 6


def test_bench_points_passes_its_options_through(monkeypatch):
    import benchmarks.point_budget

    seen = {}
    monkeypatch.setattr(benchmarks.point_budget, "run", lambda config: seen.setdefault("run", config))
    main(["bench", "points", "--task", "hand-insert", "--task", "push", "--points", "64", "--layouts", "2",
          "--crop-box=-0.6,0.25,0.005,0.6,0.97,0.7"])
    config = seen["run"]
    assert (config.tasks, config.points, config.layouts) == (("hand-insert", "push"), 64, 2)
    assert config.crop_box == ((-0.6, 0.25, 0.005), (0.6, 0.97, 0.7)) and config.backend == "render"
