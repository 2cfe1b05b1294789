"""robosuite Lift seen through a camera, as a gymnasium environment LeRobot's evaluation code drives.

* :class:`LiftEnv` — robosuite 1.4.1's ``Lift`` (Panda, OSC_POSE controller at 20 Hz) with the
  ``agentview`` camera rendered at 84x84 off-screen (``MUJOCO_GL=osmesa`` on a CPU machine). Its
  observation is what LeRobot's ``preprocess_observation`` reads: ``pixels.agentview`` (uint8
  HxWx3, rows top first) and ``agent_pos`` (end-effector position and the two gripper finger
  joints, 5 floats). The action is 4 floats in [-1, 1]: the controller's position delta
  (x, y, z; 1.0 = 5 cm per step) and the gripper (+1 closes). The episode ends when the cube is
  lifted (``is_success``) or after ``max_steps``. ``reset(seed=s)`` seeds numpy's global
  generator, which robosuite draws the cube's place and yaw and the arm's start from: a seed is an
  initial condition.
* :func:`expert_action` — a scripted expert that reads the simulator's state (the cube's
  position, which the policy never sees): over the cube, down, close, up; with per-episode
  speed and a Gaussian action noise so demonstrations differ.

The camera is rendered here rather than as a robosuite observable: ``env.sim.render`` once per
control step (the observable pipeline rendered it at every physics sub-step, 2.5x the cost).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

os.environ.setdefault("MUJOCO_GL", "osmesa")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

CAMERA = "agentview"
SIZE = 84
FPS = 20
STATE_NAMES = ["eef_x", "eef_y", "eef_z", "finger_l", "finger_r"]
ACTION_NAMES = ["dx", "dy", "dz", "gripper"]


@dataclass
class LiftConfig:
    max_steps: int = 120
    size: int = SIZE


class LiftEnv(gym.Env):  # type: ignore[misc]
    """robosuite Lift with an 84x84 agentview camera; see the module's docstring."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(self, cfg: Optional[LiftConfig] = None) -> None:
        import robosuite as suite
        from robosuite import load_controller_config

        self.cfg = cfg or LiftConfig()
        self._max_episode_steps = self.cfg.max_steps
        self.render_mode = "rgb_array"
        self.env = suite.make(
            "Lift",
            robots="Panda",
            controller_configs=load_controller_config(default_controller="OSC_POSE"),
            has_renderer=False,
            has_offscreen_renderer=True,
            use_camera_obs=False,
            use_object_obs=True,
            reward_shaping=False,
            control_freq=FPS,
            horizon=10_000,
            ignore_done=True,
            hard_reset=False,
        )
        s = self.cfg.size
        self.observation_space = gym.spaces.Dict(
            {
                "pixels": gym.spaces.Dict({CAMERA: gym.spaces.Box(0, 255, (s, s, 3), np.uint8)}),
                "agent_pos": gym.spaces.Box(-np.inf, np.inf, (5,), np.float32),
            }
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.task = "lift the cube"
        self.task_description = self.task
        self._raw: Dict[str, Any] = {}
        self._frame: Optional[np.ndarray] = None
        self.steps = 0

    def _camera(self) -> np.ndarray:
        s = self.cfg.size
        # MuJoCo renders rows bottom first.
        return np.ascontiguousarray(self.env.sim.render(camera_name=CAMERA, width=s, height=s)[::-1])

    def _obs(self) -> Dict[str, Any]:
        self._frame = self._camera()
        pos = np.concatenate([self._raw["robot0_eef_pos"], self._raw["robot0_gripper_qpos"]]).astype(np.float32)
        return {"pixels": {CAMERA: self._frame}, "agent_pos": pos}

    @property
    def cube_pos(self) -> np.ndarray:
        return np.asarray(self._raw["cube_pos"], np.float64)

    @property
    def eef_pos(self) -> np.ndarray:
        return np.asarray(self._raw["robot0_eef_pos"], np.float64)

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None) -> Tuple[Dict[str, Any], Dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            np.random.seed(seed)
        self._raw = self.env.reset()
        self.steps = 0
        return self._obs(), {"is_success": False}

    def step(self, action: np.ndarray) -> Tuple[Dict[str, Any], float, bool, bool, Dict[str, Any]]:
        a = np.clip(np.asarray(action, np.float64).reshape(-1), -1.0, 1.0)
        if a.shape != (4,):
            raise ValueError(f"Lift takes 4 action values (dx, dy, dz, gripper); got {a.shape}")
        full = np.zeros(7)
        full[:3] = a[:3]
        full[6] = a[3]
        self._raw, _, _, _ = self.env.step(full)
        self.steps += 1
        success = bool(self.env._check_success())
        truncated = self.steps >= self.cfg.max_steps and not success
        return self._obs(), float(success), success, truncated, {"is_success": success}

    def render(self) -> np.ndarray:
        return self._frame if self._frame is not None else self._camera()

    def close(self) -> None:
        self.env.close()


class Expert:
    """The scripted expert of one episode (its speed and noise drawn from ``rng``)."""

    def __init__(self, rng: np.random.Generator, noise: float = 0.15) -> None:
        self.rng = rng
        self.noise = noise
        self.gain = float(rng.uniform(7.0, 12.0))
        self.hover = float(rng.uniform(0.05, 0.09))
        self.offset = rng.normal(0.0, 0.004, 2)
        self.phase = "approach"
        self.closing = 0

    def __call__(self, env: LiftEnv) -> np.ndarray:
        cube, eef = env.cube_pos, env.eef_pos
        target = cube.copy()
        target[:2] += self.offset
        grip = -1.0
        if self.phase == "approach":
            target[2] += self.hover
            if np.linalg.norm((target - eef)[:2]) < 0.008 and abs(target[2] - eef[2]) < 0.02:
                self.phase = "descend"
        if self.phase == "descend":
            target[2] -= 0.005
            if eef[2] - cube[2] < 0.012:
                self.phase = "grasp"
        if self.phase == "grasp":
            target = eef.copy()
            grip = 1.0
            self.closing += 1
            if self.closing >= 6:
                self.phase = "lift"
        if self.phase == "lift":
            target = eef.copy()
            target[2] = cube[2] + 0.25
            grip = 1.0
        d = np.clip(self.gain * (target - eef), -1.0, 1.0)
        a = np.concatenate([d, [grip]])
        a[:3] += self.rng.normal(0.0, self.noise, 3)
        return np.clip(a, -1.0, 1.0).astype(np.float32)
