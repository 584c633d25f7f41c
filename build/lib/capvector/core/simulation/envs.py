"""Meta-World v3 environments with seeded goal variations, `state`/`pixels` observations and fast
upright offscreen rendering.

Goal variations: metaworld's benchmarks (MT1, MT50) draw 50 fixed goals per task from the global
numpy RNG. We instead let the environment sample its own goal from `env.np_random` after seeding it
with the episode's integer seed (metaworld's `seeded_rand_vec` path). That gives a reproducible goal
for *any* integer seed, with the task's own rejection rules (e.g. goal not on top of the object), so
disjoint seed ranges (demos vs validation vs evaluation) give different goals.
"""

from __future__ import annotations

import copy
import functools
import os
import warnings
from typing import TYPE_CHECKING, Any, Literal

# Offscreen rendering needs a GL platform chosen before mujoco is imported; EGL works headless (the
# user's own MUJOCO_GL wins).
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import mujoco  # noqa: E402
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

if TYPE_CHECKING:
    from metaworld.policies.policy import Policy

from capvector.core.simulation.depth_targets import PinholeCamera, patch_xyz
from capvector.core.simulation.metaworld_tasks import (
    INSTRUCTIONS,
    check_against_metaworld,
    validate_task_names,
)

CAMERAS = ("topview", "corner", "corner2", "corner3", "corner4", "behindGripper", "gripperPOV")
STATE_DIM = 39
PROPRIO_DIM = 4
PRIVILEGED_DIM = 9
ACTION_DIM = 4
MAX_HORIZON = 500  # metaworld's max_path_length: its envs refuse to step further
GOAL_SAMPLING = "capvector-seeded-rand-vec-v1"  # names the seed -> goal rule; part of eval protocols

ObsMode = Literal["state", "pixels"]

# The scripted experts warn on every step whose raw response exceeds [-1, 1]; the clip is intended.
warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high", category=UserWarning)


class EnvConfig(BaseModel):
    """One task environment: which task, what the policy observes, how long an episode may run."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    task: str
    obs_mode: ObsMode = "state"
    camera: str = "corner2"
    image_size: int = Field(64, ge=16, le=256)
    horizon: int = Field(MAX_HORIZON, ge=1, le=MAX_HORIZON)
    seed: int = Field(0, ge=0)
    patch_grid: int | None = Field(
        None,
        ge=1,
        description="pixels mode: also observe 'patch_xyz', the world point each cell of a "
        "patch_grid x patch_grid split of the image sees (from a depth render; training targets only)",
    )

    @field_validator("task")
    @classmethod
    def _known_task(cls, task: str) -> str:
        validate_task_names([task])
        return task

    @field_validator("camera")
    @classmethod
    def _known_camera(cls, camera: str) -> str:
        if camera not in CAMERAS:
            raise ValueError(f"unknown camera {camera!r}; Meta-World cameras are {', '.join(CAMERAS)}")
        return camera

    @model_validator(mode="after")
    def _patch_grid_fits(self) -> EnvConfig:
        if self.patch_grid is not None:
            if self.obs_mode != "pixels":
                raise ValueError(
                    f"patch_grid needs obs_mode 'pixels' (patches are image patches), got {self.obs_mode!r}"
                )
            if self.image_size % self.patch_grid:
                raise ValueError(f"patch_grid ({self.patch_grid}) must divide image_size ({self.image_size})")
        return self


class FastRenderer:
    """Offscreen RGB renderer at ~10x metaworld's default speed that returns upright images.

    Shadows, reflections and multisampling cost ~90% of CPU render time and add nothing a small
    policy needs. Meta-World's corner cameras look at the table with their up-axis pointing down, so
    their raw images are rotated by 180 degrees; we rotate back (a vertical flip alone would mirror
    the scene). The check uses the camera's current orientation, so tracking cameras work too.
    Depth is rendered only by `render_rgbd` (a second, unlit pass); `render` is unchanged by it.
    """

    def __init__(self, model: mujoco.MjModel, camera: str, size: int):
        model.vis.quality.offsamples = 0  # must precede the GL context creation
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, size)
        model.vis.global_.offheight = max(model.vis.global_.offheight, size)
        self._renderer = mujoco.Renderer(model, size, size)
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._camera = camera
        self._camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        self._size = size
        self._model = model
        self.far = float(model.vis.map.zfar * model.stat.extent)  # metres; depth of pixels seeing nothing

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """uint8 (H, W, 3) upright image of the current simulator state."""
        self._renderer.update_scene(data, camera=self._camera)
        image = self._renderer.render()
        return np.ascontiguousarray(image[::-1, ::-1]) if self._upside_down(data) else image

    def render_rgbd(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray, PinholeCamera]:
        """The upright image, its depth (float32 (H, W), metres along the optical axis; `far` where no
        geometry is seen) and the pinhole camera of that upright view, from one scene update."""
        renderer = self._renderer
        renderer.update_scene(data, camera=self._camera)
        image = renderer.render()
        renderer.enable_depth_rendering()
        try:
            depth = renderer.render()
        finally:
            renderer.disable_depth_rendering()
        model, cid = self._model, self._camera_id
        if model.cam_orthographic[cid] or np.any(model.cam_sensorsize[cid]):
            raise ValueError(f"camera {self._camera!r} is not a fovy pinhole camera; depth targets need one")
        rotation = data.cam_xmat[cid].reshape(3, 3).copy()
        if self._upside_down(data):
            image, depth = np.ascontiguousarray(image[::-1, ::-1]), np.ascontiguousarray(depth[::-1, ::-1])
            rotation[:, :2] *= -1  # the turned image's right and up are the camera's left and down
        camera = PinholeCamera(data.cam_xpos[cid].copy(), rotation, float(model.cam_fovy[cid]), self._size)
        return image, depth, camera

    def _upside_down(self, data: mujoco.MjData) -> bool:
        return data.cam_xmat[self._camera_id][7] < 0  # world z of the camera's y (up) axis

    def close(self) -> None:
        self._renderer.close()


@functools.cache
def _compiled_model(xml_path: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(xml_path)


def _initialize_from_cache(self: Any) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """gymnasium's MujocoEnv._initialize_simulation, but copying a compiled model (6-15 ms) instead of
    parsing the XML again (115 ms), or taking the `SharedModel` the env is built on (see `_build_env`)."""
    share: SharedModel | None = self.__dict__.pop("_capvector_share", None)
    if share is None:
        model = copy.copy(_compiled_model(self.fullpath))
    else:
        model = share.model_for_new_env(self.fullpath)
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
    # On by default, this viewer flag makes every mj_step clear one byte per BVH node (134k here, mostly
    # mesh nodes): a quarter of all instructions, and cache-cold in evaluation's batches. No physics.
    model.vis.global_.bvactive = 0
    return model, mujoco.MjData(model)


@functools.cache
def _env_class(task: str) -> type:
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS  # here, not at import: configs validate without it

    check_against_metaworld()
    base = ALL_V3_ENVIRONMENTS[task]
    return type(base.__name__, (base,), {"_initialize_simulation": _initialize_from_cache})


def _build_env(task: str, share: SharedModel | None = None) -> Any:
    """Meta-World's goal-observable recipe (env_dict._create_observable_goal_envs) with our seeding:
    the goal is part of the state, and each reset samples its goal from the env's seeded RNG."""
    cls = _env_class(task)
    env = cls.__new__(cls)
    if share is not None:
        env._capvector_share = share  # read (and removed) by _initialize_from_cache inside __init__
    env.__init__()
    env._partially_observable = False
    del env.sawyer_observation_space  # cached with the goal hidden; recomputed with goal bounds
    env._set_task_called = True
    env._freeze_rand_vec = False
    env.seeded_rand_vec = True
    return env


# The model arrays Meta-World writes: body and site positions at reset, the mocap weld at construction.
# tests/test_envs.py checks on every task that nothing else in the model changes.
EPISODE_MODEL_FIELDS = ("body_pos", "site_pos", "eq_data")


class SharedModel:
    """One task's model and renderer shared by envs that are stepped in turn (evaluation's batches).

    A model is 21 MB (meshes, textures); copying it for each of 64 parallel episodes cost more than
    all the other evaluation overhead together. Meta-World writes episode values into the model
    (`EPISODE_MODEL_FIELDS`), so each env keeps its own copy of those arrays and loads it before it
    touches the simulator: every env computes exactly what it would with a model of its own.
    """

    def __init__(self, config: EnvConfig):
        self.config = config
        self.model: mujoco.MjModel | None = None
        self._views: list[np.ndarray] = []
        self._pristine: list[np.ndarray] = []
        self._owner: MetaWorldEnv | None = None
        self._renderers: dict[int, FastRenderer] = {}

    def new_env(self) -> MetaWorldEnv:
        return MetaWorldEnv(self.config, share=self)

    def model_for_new_env(self, xml_path: str) -> mujoco.MjModel:
        """The model in the state a fresh copy would have (the current owner's arrays saved first)."""
        if self.model is None:
            self.model = copy.copy(_compiled_model(xml_path))
            self._views = [getattr(self.model, name) for name in EPISODE_MODEL_FIELDS]
            self._pristine = [view.copy() for view in self._views]
        self._switch(None, self._pristine)
        return self.model

    def adopt(self, env: MetaWorldEnv) -> list[np.ndarray]:
        """Make a just-built env the owner; returns its copy of the episode arrays."""
        self._owner = env
        return [view.copy() for view in self._views]

    def activate(self, env: MetaWorldEnv) -> None:
        if self._owner is not env:
            self._switch(env, env._model_arrays)

    def _switch(self, env: MetaWorldEnv | None, arrays: list[np.ndarray]) -> None:
        if self._owner is not None:
            for saved, view in zip(self._owner._model_arrays, self._views, strict=True):
                saved[...] = view
        for view, mine in zip(self._views, arrays, strict=True):
            view[...] = mine
        self._owner = env

    def renderer(self, size: int) -> FastRenderer:
        """The shared renderer of side `size` (the policy's images, or a video's frames)."""
        if size not in self._renderers:
            self._renderers[size] = FastRenderer(self.model, self.config.camera, size)
        return self._renderers[size]

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers = {}


class MetaWorldEnv:
    """One Meta-World v3 task with the goal visible to the expert and observations per the contract.

    `reset(seed)` fixes the goal variation; `step(action)` returns (obs, reward, success, info).
    Observation dict: "state" f32 (39,) Meta-World's observation; "proprio" f32 (4,) hand xyz and
    gripper opening (state[0:4]); "privileged" f32 (9,) object xyz, goal xyz, gripper (tool centre
    point) xyz read from the simulator (unclipped, unlike the state vector); "image" uint8 (H, W, 3)
    only in pixels mode; "patch_xyz" f32 (patch_grid², 3) only with `config.patch_grid`: the world
    point each image patch sees (row-major, NaN for a patch seeing no geometry; depth_targets.py).
    Built by a `SharedModel`, it must be used through these methods only (`.env`
    may hold another env's episode values in its model).
    """

    def __init__(self, config: EnvConfig, share: SharedModel | None = None):
        self.config = config
        self.instruction = INSTRUCTIONS[config.task]
        self._share = share
        self.env = _build_env(config.task, share)
        if share is not None:
            self._model_arrays = share.adopt(self)
        self._renderer: FastRenderer | None = None  # the policy's images
        self._video_renderers: dict[int, FastRenderer] = {}  # by side: other sizes (videos)
        self.seed: int | None = None
        self.steps = 0

    @property
    def task(self) -> str:
        return self.config.task

    def reset(self, seed: int | None = None) -> dict[str, np.ndarray]:
        """Start an episode whose goal variation is a pure function of `seed` (default: config.seed)."""
        return self._observation(self.reset_state(seed))

    def reset_state(self, seed: int | None = None) -> np.ndarray:
        """`reset` returning Meta-World's float64 state, no observation dict: evaluation builds the
        policy's observations only when it calls the policy (`batch_observations`)."""
        seed = self.config.seed if seed is None else seed
        if not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"episode seed must be a non-negative integer, got {seed!r}")
        self._activate()
        self.env.seed(int(seed))
        state, _ = self.env.reset()
        self.seed, self.steps = int(seed), 0
        return state

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, dict[str, Any]]:
        """Apply one action in [-1, 1]^4 (dx, dy, dz, gripper); success is Meta-World's info flag."""
        action = np.asarray(action, dtype=np.float32)
        if action.shape != (ACTION_DIM,) or not np.all(np.isfinite(action)):
            raise ValueError(f"action must be {ACTION_DIM} finite numbers, got {action!r}")
        state, reward, success, info = self.step_state(action)
        return self._observation(state), reward, success, info

    def step_state(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        """`step` for an action already checked to be 4 finite float32 numbers (evaluation checks whole
        chunks at once), returning Meta-World's float64 state instead of the observation dict."""
        if self.seed is None:
            raise RuntimeError("call reset(seed) before step()")
        if self.steps >= self.config.horizon:
            raise RuntimeError(f"episode already reached its horizon of {self.config.horizon} steps; reset()")
        self._activate()
        state, reward, _, _, info = self.env.step(np.clip(action, -1.0, 1.0))
        self.steps += 1
        return state, float(reward), bool(info["success"]), info

    @property
    def goal(self) -> np.ndarray:
        """The goal position of the current episode (world xyz)."""
        self._activate()
        return np.array(self.env._target_pos, dtype=np.float32)

    def privileged(self) -> np.ndarray:
        """Object xyz, goal xyz, gripper xyz from the simulator: training-only scene features."""
        self._activate()
        env = self.env
        parts = [env._get_pos_objects()[:3], env._target_pos, env.tcp_center]
        return np.concatenate(parts).astype(np.float32)

    def render(self, size: int | None = None) -> np.ndarray:
        """Upright uint8 (S, S, 3) image from the configured camera (works in both modes). `size`: S,
        by default `config.image_size` (what the policy sees); another size (a video's frames) renders
        with a renderer of its own, so the policy's images stay what they are without it."""
        return self._fast_renderer(size).render(self.env.data)

    def render_rgbd(self) -> tuple[np.ndarray, np.ndarray, PinholeCamera]:
        """`render` plus the depth (metres) and the pinhole camera of the upright view (see FastRenderer)."""
        return self._fast_renderer().render_rgbd(self.env.data)

    def _fast_renderer(self, size: int | None = None) -> FastRenderer:
        self._activate()
        if size is None or size == self.config.image_size:
            if self._renderer is None:
                self._renderer = self._new_renderer(self.config.image_size)
            return self._renderer
        if size not in self._video_renderers:
            self._video_renderers[size] = self._new_renderer(size)
        return self._video_renderers[size]

    def _new_renderer(self, size: int) -> FastRenderer:
        if self._share is not None:
            return self._share.renderer(size)
        return FastRenderer(self.env.model, self.config.camera, size)

    def _activate(self) -> None:
        if self._share is not None:
            self._share.activate(self)

    def _observation(self, state: np.ndarray) -> dict[str, np.ndarray]:
        state = state.astype(np.float32)
        obs = {"state": state, "proprio": state[:PROPRIO_DIM].copy(), "privileged": self.privileged()}
        if self.config.patch_grid is not None:
            obs["image"], depth, camera = self.render_rgbd()
            obs["patch_xyz"] = patch_xyz(depth, camera, self.config.patch_grid, self._renderer.far)
        elif self.config.obs_mode == "pixels":
            obs["image"] = self.render()
        return obs

    def close(self) -> None:
        """Free the GL context first (avoids EGL errors at interpreter exit), then the simulator."""
        if self._share is None:  # shared ones are the share's to close
            for renderer in [self._renderer, *self._video_renderers.values()]:
                if renderer is not None:
                    renderer.close()
        self._renderer, self._video_renderers = None, {}
        self.env.close()

    def __enter__(self) -> MetaWorldEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@functools.cache
def expert_policy(task: str) -> Policy:
    """Meta-World's scripted expert for `task` (stateless: it reads only the current state)."""
    from metaworld.policies import ENV_POLICY_MAP

    validate_task_names([task])
    check_against_metaworld()
    return ENV_POLICY_MAP[task]()


def expert_action(task: str, state: np.ndarray) -> np.ndarray:
    """The expert's action for one 39-number state, clipped to the action box as the env would."""
    return np.clip(expert_policy(task).get_action(state), -1.0, 1.0).astype(np.float32)


def batch_observations(states: list[np.ndarray], privileged: list[np.ndarray]) -> dict[str, np.ndarray]:
    """The (B, ...) state, proprio and privileged arrays of the observation contract from Meta-World
    states and `MetaWorldEnv.privileged()` vectors, straight into batch arrays (images: the caller's)."""
    state = np.array(states, dtype=np.float32)
    return {"state": state, "proprio": state[:, :PROPRIO_DIM].copy(), "privileged": np.array(privileged)}
