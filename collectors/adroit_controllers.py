"""Adroit controllers: state-feedback experts with a fixed grasp and phase logic.

The planning experts (:mod:`collectors.adroit_experts`) succeed but take a different path in
every episode, and ten such demonstrations do not pin down one behaviour a policy can
imitate. A controller here is a deterministic function of the scene's state: its phase
(reach, grasp, turn, pull...) follows from positions alone, its arm targets from damped
least-squares inverse kinematics on the true model, so the same state always gets the same
action, as from DP3's and MP1's trained RL agents. Pen's controller is open loop: it plays the
sequence library's actions for its target (:mod:`collectors.pen_sequences`).

Adroit's actuators are position servos whose force is ``gain * ctrl - bias * q``; the arm's
(gain 500, bias 200) hold ``q = 2.5 ctrl``, not ``ctrl``. :meth:`HandKinematics.action`
converts joint-position targets into the controls that hold them against gravity, then into
the env's normalised actions.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from collectors.pen_sequences import DEFAULT_LIBRARY, cached_library, target_roll_pitch
from d2a_envs.suites.adroit import AdroitEnv, set_physics

FINGER_FLEXION = tuple(f"{finger}J{joint}" for finger in ("FF", "MF", "RF", "LF") for joint in (2, 1, 0))


class HandKinematics:
    """Joint bookkeeping, inverse kinematics and the action map of one Adroit model.

    Example:
        >>> kinematics = HandKinematics(env.model, *env.action_map)
        >>> targets = kinematics.hold(data)           # every actuated joint where it is
        >>> action = kinematics.action(data, targets)  # normalised, in [-1, 1]
    """

    def __init__(self, model: mujoco.MjModel, action_mean: np.ndarray, action_scale: np.ndarray) -> None:
        self.model = model
        self._scratch = mujoco.MjData(model)
        self._action_mean, self._action_scale = np.asarray(action_mean), np.asarray(action_scale)
        joints = model.actuator_trnid[:, 0]
        self.actuator_of = {model.joint(j).name: index for index, j in enumerate(joints)}
        self._qpos_of_actuator = model.jnt_qposadr[joints]
        self._dof_of_actuator = model.jnt_dofadr[joints]

    def qpos(self, data: mujoco.MjData, joint: str) -> float:
        return float(data.qpos[self.model.jnt_qposadr[self.model.joint(joint).id]])

    def hold(self, data: mujoco.MjData) -> np.ndarray:
        """Position targets (one per actuator) equal to the current joint positions."""
        return data.qpos[self._qpos_of_actuator].copy()

    def solve(self, data: mujoco.MjData, site: str, goal: np.ndarray, joints: tuple[str, ...],
              fixed: dict[str, float] | None = None, iterations: int = 30, damping: float = 1e-3) -> np.ndarray:
        """Positions of ``joints`` that bring ``site`` to ``goal`` (others as in ``data``, or ``fixed``).

        Damped least squares from the current pose, clipped to the joint ranges; the result
        is the nearest reachable pose when ``goal`` is out of reach.
        """
        model, scratch = self.model, self._scratch
        scratch.qpos[:] = data.qpos
        for joint, value in (fixed or {}).items():
            scratch.qpos[model.jnt_qposadr[model.joint(joint).id]] = value
        ids = [model.joint(joint).id for joint in joints]
        qpos, dofs = model.jnt_qposadr[ids], model.jnt_dofadr[ids]
        low, high = model.jnt_range[ids].T
        site_id = model.site(site).id
        jacobian = np.zeros((3, model.nv))
        for _ in range(iterations):
            mujoco.mj_kinematics(model, scratch)
            mujoco.mj_comPos(model, scratch)
            error = goal - scratch.site_xpos[site_id]
            mujoco.mj_jacSite(model, scratch, jacobian, None, site_id)
            arm = jacobian[:, dofs]
            step = arm.T @ np.linalg.solve(arm @ arm.T + damping * np.eye(3), error)
            scratch.qpos[qpos] = np.clip(scratch.qpos[qpos] + step, low, high)
        return scratch.qpos[qpos].copy()

    def lead(self, data: mujoco.MjData, joints: tuple[str, ...], solution: np.ndarray,
             gain: float) -> dict[str, float]:
        """Targets for ``joints``, ``gain`` times the way from where they are to ``solution``
        (1: the solution itself; above 1 the servos pull harder towards it)."""
        return {joint: self.qpos(data, joint) + gain * (value - self.qpos(data, joint))
                for joint, value in zip(joints, solution, strict=True)}

    def targets(self, joints: dict[str, float]) -> np.ndarray:
        """One position target per actuator: ``joints`` by name, 0 for the others."""
        targets = np.zeros(self.model.nu)
        for joint, value in joints.items():
            targets[self.actuator_of[joint]] = value
        return targets

    def action(self, data: mujoco.MjData, targets: np.ndarray) -> np.ndarray:
        """The normalised action whose servos hold ``targets`` (one per actuator) against the
        current bias forces (gravity, Coriolis), clipped to [-1, 1]."""
        gain, bias = self.model.actuator_gainprm[:, 0], -self.model.actuator_biasprm[:, 1]
        ctrl = (bias * targets + data.qfrc_bias[self._dof_of_actuator]) / gain
        return np.clip((ctrl - self._action_mean) / self._action_scale, -1.0, 1.0)


def _grasp(closure: float, thumb: dict[str, float]) -> dict[str, float]:
    """Hand targets of a grasp: every finger flexed to ``closure``, the thumb as given."""
    return {**dict.fromkeys(FINGER_FLEXION, closure), **thumb}


def _rotate_z(vector: np.ndarray, angle: float) -> np.ndarray:
    """``vector`` (2 or 3 components) turned by ``angle`` about the z axis."""
    c, s = np.cos(angle), np.sin(angle)
    turned = np.array([c * vector[0] - s * vector[1], s * vector[0] + c * vector[1]])
    return np.r_[turned, vector[2:]]


def _rotate_y(vector: np.ndarray, angle: float) -> np.ndarray:
    """``vector`` turned by ``angle`` about the y axis (the latch's axis)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c * vector[0] + s * vector[2], vector[1], -s * vector[0] + c * vector[2]])


@dataclass(frozen=True)
class DoorControllerConfig:
    """Settings of :func:`door_action` (tuned by ``d2a bench tune-expert --task adroit-door``).

    Attributes:
        hover: height above the handle from which the palm descends (m).
        grasp_closure: finger flexion of the grasp (rad).
        turn_step: the latch angle the palm leads the handle by while turning it (rad).
        unlatched: latch angle from which the door is pulled (rad).
        pull_step: the door angle the palm leads the handle by while pulling (rad).
        pull_roll: forearm roll beyond the latch angle while pulling (rad).
        release_at: door angle at which the hand lets go and goes round the door (rad).
        push_step: the door angle the palm leads the door's inner face by while pushing (rad).
        round_x, round_y: the waypoints round the door's free edge, in the door's frame (m).
        push_x, push_y: the pushing point on the door's inner face, in the door's frame (m).
        push_height: height of the palm while it goes round and pushes (m).
        arm_gain, round_gain: arm targets lead the current pose by this multiple of the
            inverse-kinematics step (1: the solution itself), holding and going round.
    """

    hover: float = 0.05
    grasp_closure: float = 0.953
    turn_step: float = 0.976
    unlatched: float = 1.1
    pull_step: float = 0.723
    pull_roll: float = 1.121
    release_at: float = 0.483
    push_step: float = 0.3
    round_x: float = -0.685
    round_y: float = 0.097
    push_x: float = -0.405
    push_y: float = 0.068
    push_height: float = 0.16
    arm_gain: float = 1.743
    round_gain: float = 1.72


_DOOR_ARM = ("ARTz", "ARRx", "ARRy")
_DOOR_THUMB = {"THJ3": 1.0, "THJ4": 0.5}  # across the lever, against the curled fingers


def door_action(kinematics: HandKinematics, data: mujoco.MjData, config: DoorControllerConfig) -> np.ndarray:
    """The door controller's action in the state of ``data``.

    Grasps the lever from above, turns it by rolling the forearm while the palm follows the
    lever's arc, pulls the door along its arc, lets go at ``release_at``, goes round the
    free edge and pushes the door open from inside.
    """
    model = kinematics.model
    palm = data.site("S_grasp").xpos.copy()
    handle = data.site("S_handle").xpos.copy()
    latch_axis = data.xanchor[model.joint("latch").id].copy()
    hinge_axis = data.xanchor[model.joint("door_hinge").id].copy()
    latch, hinge = kinematics.qpos(data, "latch"), kinematics.qpos(data, "door_hinge")
    closure = float(np.mean([kinematics.qpos(data, joint) for joint in FINGER_FLEXION]))
    to_handle = float(np.linalg.norm(palm - handle))
    roll, closed, gain = 0.0, True, config.arm_gain

    if hinge > config.release_at or (hinge > 0.5 and to_handle > 0.06):
        closed, gain = False, config.round_gain
        in_door = _rotate_z(palm[:2] - hinge_axis[:2], -hinge)  # the palm in the door's frame
        height = config.push_height
        if closure > 0.4:  # let go: back off and down, off the lever
            local, height = in_door + np.array([0.0, -0.04]), palm[2] - 0.04
        elif in_door[1] < 0.06 and in_door[0] > config.round_x + 0.05:  # outside: out past the free edge
            local = np.array([config.round_x, min(in_door[1], -0.12)])
        elif in_door[1] < 0.06:  # past the edge: round it
            local = np.array([config.round_x, config.round_y])
        else:  # inside: push the inner face ahead of where it is
            local = _rotate_z(np.array([config.push_x, config.push_y]), config.push_step)
        goal = np.r_[hinge_axis[:2] + _rotate_z(local, hinge), height]
        if closure > 0.4 or to_handle < 0.1:
            roll = kinematics.qpos(data, "ARRz")  # keep the lever clear while the hand opens
    elif latch > config.unlatched or hinge > 0.05:
        goal = hinge_axis + _rotate_z(handle - hinge_axis, config.pull_step)
        roll = latch + config.pull_roll
    elif to_handle < 0.025 or (closure > 0.6 and to_handle < 0.05):
        goal = handle
        if closure > 0.8 * config.grasp_closure:  # grasped: turn the lever
            goal = latch_axis + _rotate_y(handle - latch_axis, config.turn_step)
            roll = latch + config.turn_step
    elif np.linalg.norm(palm[:2] - handle[:2]) > 0.02:
        goal, closed = handle + np.array([0.0, 0.0, config.hover]), False
    else:
        goal, closed = handle, False

    solution = kinematics.solve(data, "S_grasp", goal, _DOOR_ARM, fixed={"ARRz": roll})
    joints = {**kinematics.lead(data, _DOOR_ARM, solution, gain), "ARRz": roll}
    if closed:
        joints.update(_grasp(config.grasp_closure, _DOOR_THUMB))
    return kinematics.action(data, kinematics.targets(joints))


@dataclass(frozen=True)
class HammerControllerConfig:
    """Settings of :func:`hammer_action`.

    Attributes:
        grasp_x, grasp_y, grasp_z: the grasp point on the hammer's neck, from where every
            reset puts the hammer's origin (its handle, HAMMER_START) (m). A fixed point: a target
            that followed the hammer would chase it as the closing fingers push it.
        hover: height above the grasp point from which the palm descends (m).
        grasp_closure: finger flexion of the grasp (rad).
        lift: height above the grasp point the palm lifts the hammer to (m).
        deviation: wrist deviation that turns the held hammer's head forwards (rad).
        extension: wrist flexion while aiming and striking (rad, negative: extension).
        pitch_gain: forearm pitch change per metre of the head's height error (rad / m).
        aim_yaw: forearm yaw the strike starts from (rad).
        swing: forearm yaw change per control step of the strike (rad).
        aligned: head-to-nail height error under which the strike goes on (m).
        arm_gain: arm targets lead the current pose by this multiple of the inverse-kinematics
            step while grasping.
    """

    grasp_x: float = -0.08
    grasp_y: float = -0.01
    grasp_z: float = -0.005
    hover: float = 0.06
    grasp_closure: float = 1.5
    lift: float = 0.14
    deviation: float = -0.79
    extension: float = -0.5
    pitch_gain: float = 1.5
    aim_yaw: float = 0.3
    swing: float = 0.3
    aligned: float = 0.02
    arm_gain: float = 1.0


_HAMMER_ARM = ("ARRx", "ARRy", "WRJ1")
HAMMER_START = np.array([0.0, -0.2, 0.035])  # the hammer's origin after every reset (the board alone moves)
# The thumb's opposition for the neck grasp: its tip meets the curled fingers under the palm.
_HAMMER_THUMB = {"THJ4": 0.0, "THJ3": 1.3, "THJ2": 0.26, "THJ1": -0.52, "THJ0": -1.57}


def hammer_action(kinematics: HandKinematics, data: mujoco.MjData, config: HammerControllerConfig) -> np.ndarray:
    """The hammer controller's action in the state of ``data``.

    Grasps the neck from above (fingers curled under it, the thumb opposed), lifts, turns the
    head forwards with the wrist, matches the head's height to the nail's with the forearm's
    pitch, and strikes by sweeping the forearm's yaw: the head drives the nail sideways, along
    its axis.
    """
    model = kinematics.model
    palm = data.site("S_grasp").xpos.copy()
    hammer = data.xpos[model.body("Object").id].copy()
    head, nail = data.site("tool").xpos.copy(), data.site("S_target").xpos.copy()
    closure = float(np.mean([kinematics.qpos(data, joint) for joint in FINGER_FLEXION]))
    grasp = HAMMER_START + np.array([config.grasp_x, config.grasp_y, config.grasp_z])
    to_grasp = float(np.linalg.norm(palm - grasp))
    closed = True
    if hammer[2] > 0.06 and closure > 0.65 * config.grasp_closure:  # held off the table: aim, then strike
        pitch = kinematics.qpos(data, "ARRx") + config.pitch_gain * (head[2] - nail[2])
        yaw = kinematics.qpos(data, "ARRy")
        turned = abs(kinematics.qpos(data, "WRJ0") - config.deviation) < 0.1
        if turned and abs(head[2] - nail[2]) < config.aligned and (yaw < config.aim_yaw - 0.05 or head[0] < nail[0]):
            yaw -= config.swing  # strike: sweep the head along the nail's axis
        else:
            yaw = config.aim_yaw
        joints = {"ARRx": pitch, "ARRy": yaw, "WRJ1": config.extension, "WRJ0": config.deviation}
    else:
        if closure > 0.65 * config.grasp_closure and to_grasp < 0.06:  # grasped (the neck stops the fingers): lift
            goal = grasp + np.array([0.0, 0.0, config.lift])
        elif (closure > 0.2 and to_grasp < 0.06) or (np.linalg.norm(palm[:2] - grasp[:2]) < 0.05
                                                     and palm[2] < grasp[2] + 0.016):
            goal = grasp
        elif np.linalg.norm(palm[:2] - grasp[:2]) > 0.04:
            goal, closed = grasp + np.array([0.0, 0.0, config.hover]), False
        else:
            goal, closed = grasp, False
        solution = kinematics.solve(data, "S_grasp", goal, _HAMMER_ARM)
        joints = kinematics.lead(data, _HAMMER_ARM, solution, config.arm_gain)
    if closed:
        joints.update(_grasp(config.grasp_closure, _HAMMER_THUMB))
    return kinematics.action(data, kinematics.targets(joints))


@dataclass(frozen=True)
class PenControllerConfig:
    """Settings of :func:`pen_action`.

    Attributes:
        library: the sequence library (:mod:`collectors.pen_sequences`; the one shipped by default).
        control_period: seconds per control step (Pen: 5 physics steps of 2 ms), which turns
            the state's clock into the step of the sequence.
        blend: play the bilinear blend of the four nodes around the target instead of the
            nearest node's sequence (on the shipped library: 60 against 96 of 100 layouts).
    """

    library: str = str(DEFAULT_LIBRARY)
    control_period: float = 0.01
    blend: bool = False


def pen_action(kinematics: HandKinematics, data: mujoco.MjData, config: PenControllerConfig) -> np.ndarray:
    """The library's action for the target's roll and pitch at the step the state's clock says:
    open loop, since every episode starts from the same state."""
    roll, pitch = target_roll_pitch(kinematics.model.body_quat[kinematics.model.body("target").id])
    step = round(data.time / config.control_period)
    return np.clip(cached_library(config.library).action(roll, pitch, step, config.blend), -1.0, 1.0)


CONTROLLERS = {"door": (door_action, DoorControllerConfig), "hammer": (hammer_action, HammerControllerConfig),
               "pen": (pen_action, PenControllerConfig)}


class ControllerReplica:
    """A copy of one task's scene that runs the task's controller on ``physics`` vectors.

    Example:
        >>> replica = ControllerReplica("door")
        >>> action = replica.act(observation["physics"])  # env made with physics_obs=True
    """

    def __init__(self, task: str, settings: object | None = None) -> None:
        if task not in CONTROLLERS:
            raise ValueError(f"no controller for Adroit {task!r}: controllers exist for {sorted(CONTROLLERS)}")
        scene = AdroitEnv(task, state_obs=False)
        self.task = task
        self.model = mujoco.MjModel.from_xml_path(scene.model_path)
        self.data = mujoco.MjData(self.model)
        self.kinematics = HandKinematics(self.model, *scene.action_map)
        scene.close()
        self.control, settings_type = CONTROLLERS[task]
        self.settings = settings if settings is not None else settings_type()

    def act(self, physics: np.ndarray) -> np.ndarray:
        """The controller's action in the state ``physics`` describes."""
        set_physics(self.model, self.data, self.task, physics)
        mujoco.mj_forward(self.model, self.data)  # the bias forces the servos must hold against
        return self.control(self.kinematics, self.data, self.settings)
