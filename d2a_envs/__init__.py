"""D2A environments: Meta-World and Adroit tasks with 3D point-cloud observations.

Importing this package registers the ``D2A-*`` Gymnasium ids::

    import gymnasium as gym
    import d2a_envs

    env = gym.make("D2A-MetaWorld-Hammer-v0")          # raycast depth, 1024 points
    obs, info = env.reset(seed=0)
    obs["point_cloud"].shape                           # (1024, 3), world frame, metres
"""

from d2a_envs.gl import configure_mujoco_gl

configure_mujoco_gl()  # before anything imports mujoco

from d2a_envs.defaults import DEFAULT_MAX_EPISODE_STEPS, SUITE_DEFAULTS, default_config  # noqa: E402
from d2a_envs.factory import env_crop_box, make_env, task_config  # noqa: E402
from d2a_envs.registration import register_all  # noqa: E402
from d2a_envs.sampling import CropBox  # noqa: E402
from d2a_envs.sensor import PointCloudConfig, PointCloudSensor  # noqa: E402
from d2a_envs.tasks import TASKS, TaskSpec, get_task, list_tasks  # noqa: E402
from d2a_envs.wrappers import PointCloudObservation  # noqa: E402

register_all()

__all__ = [
    "CropBox", "DEFAULT_MAX_EPISODE_STEPS", "PointCloudConfig",
    "PointCloudObservation", "PointCloudSensor", "SUITE_DEFAULTS", "TASKS", "TaskSpec", "default_config",
    "env_crop_box", "get_task", "list_tasks",
    "make_env", "task_config",
]
