"""Per-patch 3D targets: pinhole back-projection, patch medians, rendered depth against the simulator,
the `patch_xyz` dataset field, and the `spatial_depth` objective that trains on it."""

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from capvector.core.policies.base import build_policy
from capvector.core.simulation.demos import DemoConfig, DemoDataset, collect_demos
from capvector.core.simulation.depth_targets import PinholeCamera, patch_medians, patch_xyz
from capvector.core.simulation.envs import EnvConfig, MetaWorldEnv
from capvector.core.training.aux_objectives import build_objective, known_objectives
from capvector.core.training.trainer import AuxConfig, TrainConfig, train

# 16-pixel images, two stride-2 convs: a 4 x 4 token grid, so demos are collected with patch_grid=4
POLICY = dict(
    obs_mode="pixels",
    image_size=16,
    stem_channels=[8, 8],
    d_model=32,
    n_layers=2,
    n_heads=4,
    chunk_size=4,
    vocab_size=64,
    max_instruction_tokens=6,
)


def _rotation(yaw: float, pitch: float) -> np.ndarray:
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return rz @ rx


def test_pinhole_conventions_by_hand():
    """fovy 90° on a 2-pixel image: focal 1 pixel, pixel centres ±0.5 from the axis; row 0 is up."""
    camera = PinholeCamera(np.array([1.0, 2.0, 3.0]), np.eye(3), 90.0, 2)
    assert camera.focal == pytest.approx(1.0)
    points = camera.backproject(np.array([[2.0, 2.0], [4.0, 4.0]]))
    expected = np.array(
        [
            [[-1.0, 1.0, -2.0], [1.0, 1.0, -2.0]],  # top row: up (+y); left column: -x
            [[-2.0, -2.0, -4.0], [2.0, -2.0, -4.0]],
        ]
    ) + [1.0, 2.0, 3.0]
    np.testing.assert_allclose(points, expected, atol=1e-12)


def test_project_inverts_backproject_for_any_pose():
    rng = np.random.default_rng(0)
    camera = PinholeCamera(rng.normal(size=3), _rotation(0.7, -2.1), 60.0, 32)
    depth = rng.uniform(0.5, 3.0, size=(32, 32))
    pixels, depths = camera.project(camera.backproject(depth))
    rows, cols = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")
    np.testing.assert_allclose(pixels[..., 0], rows, atol=1e-9)
    np.testing.assert_allclose(pixels[..., 1], cols, atol=1e-9)
    np.testing.assert_allclose(depths, depth, rtol=1e-12)
    with pytest.raises(ValueError, match=r"depth must be \(32, 32\)"):
        camera.backproject(depth[:4])


def test_patch_medians_are_row_major_and_skip_background():
    rows, cols = np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij")
    points = np.stack([rows, cols, rows * 10 + cols], axis=-1)
    valid = np.ones((4, 4), dtype=bool)
    valid[0:2, 2:4] = False  # patch 1 (top right) sees nothing
    valid[2, 0] = False  # patch 2 (bottom left) loses one of its four pixels
    out = patch_medians(points, valid, 2)
    assert out.dtype == np.float32 and out.shape == (4, 3)
    np.testing.assert_allclose(out[0], [0.5, 0.5, 5.5])
    assert np.isnan(out[1]).all()
    np.testing.assert_allclose(out[2], [3.0, 1.0, 30.0])  # its pixels (2, 1), (3, 0), (3, 1)
    np.testing.assert_allclose(out[3], [2.5, 2.5, 27.5])
    with pytest.raises(ValueError, match="does not divide"):
        patch_medians(points, valid, 3)


@pytest.mark.parametrize("size,grid", [(64, 4), (12, 3), (8, 8)])
def test_patch_medians_match_numpy_nanmedian(size, grid):
    rng = np.random.default_rng(size)
    points = rng.normal(size=(size, size, 3))
    valid = rng.random((size, size)) < 0.6
    valid[: size // grid, : size // grid] = False
    p = size // grid
    cells = np.where(valid[..., None], points, np.nan).reshape(grid, p, grid, p, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the all-NaN first patch
        expected = np.nanmedian(cells.transpose(0, 2, 1, 3, 4).reshape(grid * grid, p * p, 3), axis=1)
    np.testing.assert_allclose(patch_medians(points, valid, grid), expected.astype(np.float32), rtol=1e-6)


def test_far_plane_pixels_are_background():
    camera = PinholeCamera(np.zeros(3), np.eye(3), 60.0, 4)
    depth = np.full((4, 4), 100.0)
    depth[:2, :2] = 1.0
    out = patch_xyz(depth, camera, 2, far=100.0)
    assert np.isfinite(out[0]).all() and np.isnan(out[1:]).all()
    assert out[0, 2] == pytest.approx(-1.0)


@pytest.mark.parametrize(
    "task,camera",
    [("pick-place-v3", "corner2"), ("coffee-push-v3", "topview")],  # an image turned by 180°, one not
)
def test_rendered_depth_backprojects_onto_the_object(task, camera):
    """One patch per pixel: the pixel under the object's projected centre sees a point of the object."""
    config = EnvConfig(task=task, obs_mode="pixels", camera=camera, image_size=64, patch_grid=64)
    with MetaWorldEnv(config) as env:
        obs = env.reset(0)
        image, depth, pinhole = env.render_rgbd()
        np.testing.assert_array_equal(image, obs["image"])
        raw = env.env.data.cam_xmat[env._renderer._camera_id].reshape(3, 3)
        turned = camera != "topview"
        assert np.allclose(pinhole.rotation, raw * [-1, -1, 1] if turned else raw)
        background = depth >= 0.99 * env._renderer.far
    assert obs["patch_xyz"].dtype == np.float32 and obs["patch_xyz"].shape == (64 * 64, 3)
    obj = obs["privileged"][:3]
    row, col = pinhole.project(obj[None])[0][0]
    seen = obs["patch_xyz"][int(row) * 64 + int(col)]
    assert np.linalg.norm(seen - obj) < 0.04, (seen, obj)  # the object's surface, within its size
    assert background.any() == turned  # corner2 sees the sky box, topview only the room
    assert np.isnan(obs["patch_xyz"][background.reshape(-1)]).all()


def test_patch_grid_needs_pixels_and_must_divide_the_image():
    with pytest.raises(ValidationError, match="needs obs_mode 'pixels'"):
        EnvConfig(task="reach-v3", patch_grid=4)
    with pytest.raises(ValidationError, match=r"patch_grid \(5\) must divide image_size \(64\)"):
        DemoConfig(tasks=["reach-v3"], obs_mode="pixels", patch_xyz=True, patch_grid=5)


def test_patch_fields_are_left_out_of_the_dump_when_off():
    """Cache keys hold the demo config's dump: configs without patch_xyz dump as they did before."""
    off = DemoConfig(tasks=["reach-v3"], obs_mode="pixels")
    assert "patch_xyz" not in off.model_dump(mode="json") and "patch_grid" not in off.model_dump_json()
    on = DemoConfig(tasks=["reach-v3"], obs_mode="pixels", patch_xyz=True, patch_grid=8)
    assert on.model_dump(mode="json")["patch_grid"] == 8
    assert DemoConfig.model_validate(on.model_dump(mode="json")) == on


@pytest.fixture(scope="module")
def depth_demos():
    config = DemoConfig(
        tasks=["reach-v3"],
        episodes_per_task=1,
        obs_mode="pixels",
        image_size=16,
        horizon=100,
        workers=1,
        patch_xyz=True,
        patch_grid=4,
    )
    return collect_demos(config)


def test_collected_dataset_has_patch_xyz(depth_demos, tmp_path):
    patches = depth_demos.tensors["patch_xyz"]
    assert patches.dtype == torch.float32 and patches.shape == (len(depth_demos), 16, 3)
    finite = torch.isfinite(patches).all(-1)
    assert finite.float().mean() > 0.5
    assert patches[finite].abs().max() < 10  # within the room, not at the far plane
    assert "patch_xyz" not in depth_demos.normalization_stats()
    loaded = DemoDataset.load(depth_demos.save(tmp_path / "ds"))
    assert torch.equal(loaded.tensors["patch_xyz"].nan_to_num(7.0), patches.nan_to_num(7.0))


def quick(**kw) -> TrainConfig:
    base = dict(steps=40, batch_size=16, lr=3e-3, warmup_steps=5, checkpoint_every=1000, log_every=5)
    return TrainConfig(**{**base, "device": "cpu", "num_threads": 1, **kw})


def test_spatial_depth_loss_decreases(depth_demos, tmp_path):
    assert "spatial_depth" in known_objectives()
    torch.manual_seed(0)
    policy = build_policy(POLICY, "cpu")
    aux = AuxConfig(name="spatial_depth", weight=1.0, params={"hidden_dim": 64, "feature_dim": 32})
    result = train(policy, depth_demos, quick(aux=aux), tmp_path)
    rows = [json.loads(line) for line in Path(result.loss_curve_path).read_text().splitlines()]
    first, last = rows[0]["spatial_depth"], rows[-1]["spatial_depth"]
    assert math.isfinite(last) and last < 0.7 * first, (first, last)


def test_training_refuses_a_dataset_without_patch_xyz_or_with_another_grid(depth_demos, tmp_path):
    without = {k: v for k, v in depth_demos.tensors.items() if k != "patch_xyz"}
    aux = AuxConfig(name="spatial_depth")
    with pytest.raises(ValueError, match=r"'spatial_depth' needs dataset field\(s\) \['patch_xyz'\]"):
        train(build_policy(POLICY, "cpu"), DemoDataset(without, depth_demos.meta), quick(aux=aux), tmp_path)
    finer = build_policy({**POLICY, "stem_channels": [8]}, "cpu")  # an 8 x 8 token grid
    with pytest.raises(ValueError, match=r"\(N, 64, 3\).*patch_grid.*\(8 here\)"):
        train(finer, depth_demos, quick(aux=aux), tmp_path / "finer")


def test_target_is_fixed_and_sky_patches_are_skipped():
    features = build_policy(POLICY, "cpu").feature_specs()
    a = build_objective("spatial_depth", features, {"seed": 3})
    b = build_objective("spatial_depth", features, {"seed": 3})
    assert torch.equal(a.fourier, b.fourier) and not any(p is a.fourier for p in a.parameters())
    xyz = torch.randn(2, 16, 3)
    xyz[0, :5] = float("nan")
    a.fit({"patch_xyz": xyz})
    target, valid = a.target(xyz)
    assert torch.isfinite(target).all() and valid.sum() == 27
    tokens = torch.randn(2, 16, 32, requires_grad=True)
    loss = a({"obs_tokens": [tokens, tokens]}, {"patch_xyz": xyz})
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(tokens.grad).all()
    assert tokens.grad[0, :5].abs().sum() == 0 and tokens.grad[0, 5:].abs().sum() > 0
    sky = torch.full((2, 16, 3), float("nan"))
    assert a({"obs_tokens": [tokens, tokens]}, {"patch_xyz": sky}).item() == pytest.approx(1.0)
