"""The bridge contract (segs.modules.contract.GaussianMapper): the mapper implements it, the
bridge hands poses over once, as float32 copies, and registers a new view's pose once."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from segs.callbacks.bridge import SlamBridge
from segs.config import model_node
from segs.data.frame import Camera, Frame
from segs.modules.config import build_model, mapping_config, raster_config
from segs.modules.contract import GaussianMapper, MapCounts, TrainingView
from segs.modules.gaussian_mapper import GaussianMapperModule
from segs.pipeline.run_state import RunState
from segs.pipeline.sources import InterleavedSource
from segs.slam.base import MapUpdate

CAMERA = Camera(fx=40.0, fy=40.0, cx=16.0, cy=12.0, width=32, height=24)


class RecordingMapper:
    """A GaussianMapper that records what it is given."""

    def __init__(self, uses_depth: bool = False):
        self.iteration_ms: list[float] = []
        self.raster_backend = None
        self.compiled = False
        self.uses_depth = uses_depth
        self.calls: list[tuple[str, object]] = []

    def add_keyframes(self, views):
        self.calls.append(("add_keyframes", views))

    def update_poses(self, poses):
        self.calls.append(("update_poses", poses))

    def add_points(self, xyz, rgb, kf_ids):
        self.calls.append(("add_points", (xyz, rgb, kf_ids)))
        return len(xyz)

    def correct_map(self, transforms):
        self.calls.append(("correct_map", transforms))
        return 0

    def counts(self):
        return MapCounts(0, 0, 0, 0, 0.0)

    def first_view(self):
        return None

    def render_image(self, w2c, camera, kf_id=None):
        return {}

    def count_active(self, w2c, camera, threshold):
        return 0

    def training_views(self):
        return []

    def gaussians(self):
        return None

    def export_ply(self, path, cloud=None):
        return 0

    def fitted_cloud(self, steps, progress=None):
        return None

    def render_cloud(self, gaussians, w2c, camera):
        return torch.zeros(camera.height, camera.width, 3)


class FakeFrontend:
    uses_ground_truth_poses = False

    def __init__(self, kf_frames):
        self.kf_frames = kf_frames

    def prepare(self, frame):
        return frame

    def keyframe_frames(self):
        return dict(self.kf_frames)

    def process(self, frame):
        return None

    def poll(self):
        return MapUpdate()


class FakeSequence:
    name = "fake"

    def __len__(self):
        return 4

    def __getitem__(self, i):
        return Frame(index=i, timestamp=float(i), rgb=np.full((24, 32, 3), 0.5, np.float32), camera=CAMERA,
                     depth=np.full((24, 32), 1.5, np.float32))  # fmt: skip


def _pose(x: float) -> np.ndarray:
    w2c = np.eye(4)
    w2c[0, 3] = x
    return w2c


def _mapper_module() -> GaussianMapperModule:
    """A tiny SEGS mapper on the torch rasterizer."""
    node = model_node("segs", k=2, feature_dim=4, hidden=4)
    mapping = mapping_config({"view_budget": 2, "min_scene_extent": 0.5, "adam_eps": 1e-15, "num_downscales": 0, "downscale_phase": 0.1,
                              "min_schedule_steps": 0, "render_filter": "trained", "render_filter_decay": 0.95, "compile": False})
    raster = raster_config({"backend": "torch", "near": 0.01, "far": 100.0, "background": [0, 0, 0]})
    return GaussianMapperModule(build_model(node), mapping, raster, seed=0)


def test_the_mapper_module_implements_the_contract():
    module = _mapper_module()
    assert isinstance(module, GaussianMapper) and isinstance(RecordingMapper(), GaussianMapper)
    assert module.first_view() is None and module.counts() == MapCounts(0, 0, 0, module.counts().params, module.counts().mb)
    view = TrainingView(kf_id=3, frame_index=1, timestamp=1.0, image=torch.zeros(24, 32, 3, dtype=torch.uint8),
                        w2c=torch.eye(4), camera=CAMERA)  # fmt: skip
    module.add_keyframes([view])
    module.update_poses({3: torch.tensor(_pose(0.2), dtype=torch.float32), 99: torch.eye(4)})  # 99: no such view
    assert module.counts().training_views == 1 and module.first_view().w2c[0, 3] == torch.tensor(0.2)


def test_the_bridge_registers_a_new_views_pose_once_as_a_float32_copy():
    frontend, seq = FakeFrontend({0: 0, 1: 2}), FakeSequence()
    run = RunState(seq, InterleavedSource(frontend, seq))
    bridge = SlamBridge(run, feed_until=0.2, frames_per_step=None, min_initial_keyframes=1, progress=False, cache_frames=4)
    mapper = RecordingMapper()
    frontend_pose = _pose(0.5).astype(np.float32)
    update = MapUpdate(new_keyframes=[1], poses={0: _pose(0.1), 1: frontend_pose},
                       points=np.zeros((2, 3)), colors=np.zeros((2, 3), np.float32), point_kf=np.array([0, 1]))  # fmt: skip
    bridge._push(update, mapper)
    names = [name for name, _ in mapper.calls]
    assert names == ["add_keyframes", "update_poses", "add_points"]
    (view,) = mapper.calls[0][1]
    assert view.kf_id == 1 and view.frame_index == 2 and view.w2c.dtype == torch.float32
    assert set(mapper.calls[1][1]) == {0}  # the new view's pose came with the view, not a second time
    frontend_pose[0, 3] = 9.0  # the frontend editing its own array does not move the mapper's view
    assert float(view.w2c[0, 3]) == 0.5
    assert run.trained_frames() == {1: 2} and run.keyframes[1].trained  # the run's registry


def _old_layout(state: dict, renames: dict[str, str]) -> dict:
    """state under the names checkpoints had before the PrimitiveRows store."""
    back = {new: old for old, new in renames.items()}
    out = {}
    for key, value in state.items():
        name = key.removeprefix("model.")
        for new, old in sorted(back.items(), key=lambda kv: -len(kv[0])):
            if name == new or (new.endswith(".") and old.endswith(".") and name.startswith(new)):
                name = old + name[len(new):]
                break
        out["model." + name] = value
    return out


@pytest.mark.parametrize("name", ["segs", "plain_3dgs"])
def test_checkpoints_of_the_old_row_layout_load(name):
    mapping = mapping_config({"view_budget": 2, "min_scene_extent": 0.5, "adam_eps": 1e-15, "num_downscales": 0, "downscale_phase": 0.1,
                              "min_schedule_steps": 0, "render_filter": "trained", "render_filter_decay": 0.95, "compile": False})
    raster = raster_config({"backend": "torch", "near": 0.01, "far": 100.0, "background": [0, 0, 0]})
    extra = {"min_new_points": 1} if name == "segs" else {}
    make = lambda: GaussianMapperModule(build_model(model_node(name, **extra)), mapping, raster, seed=0)  # noqa: E731
    src = make()
    torch.manual_seed(0)
    src.add_points(torch.rand(30, 3), torch.rand(30, 3), torch.arange(30) % 4)
    new = src.state_dict()
    old = _old_layout(new, src.model.LEGACY_STATE_KEYS)
    assert set(old) != set(new) and any(k.endswith("kf_tags") for k in old)
    checkpoint = {"state_dict": old}
    dst = make()
    dst.on_load_checkpoint(checkpoint)
    dst.load_state_dict(checkpoint["state_dict"])  # strict: every key found under its new name
    assert all(torch.equal(v, dst.state_dict()[k]) for k, v in new.items() if torch.is_tensor(v))


@pytest.mark.parametrize("uses_depth", [False, True])
def test_the_bridge_keeps_fed_frames_compact_and_depth_only_for_a_mapper_that_reads_it(uses_depth):
    frontend, seq = FakeFrontend({0: 0, 1: 2}), FakeSequence()
    run = RunState(seq, InterleavedSource(frontend, seq))
    bridge = SlamBridge(run, feed_until=0.2, frames_per_step=None, min_initial_keyframes=1, progress=False, cache_frames=4)
    mapper = RecordingMapper(uses_depth)
    bridge._keep_depth = mapper.uses_depth  # what on_train_start reads
    run.source.track(3)
    assert sorted(bridge._cache) == [0, 1, 2] and all(d.image.dtype == torch.uint8 for d in bridge._cache.values())
    bridge._push(MapUpdate(new_keyframes=[1], poses={1: _pose(0.5)}), mapper)
    (view,) = mapper.calls[0][1]
    assert view.image.dtype == torch.uint8 and int(view.image[0, 0, 0]) == 128
    assert (view.depth is not None) == uses_depth
    if uses_depth:
        assert view.depth.dtype == torch.float32 and float(view.depth[0, 0]) == 1.5


@pytest.mark.parametrize("model, lambda_depth", [("segs", None), ("plain_3dgs", 0.0), ("plain_3dgs", 0.5)])
def test_the_mapper_keeps_a_views_depth_only_when_its_loss_reads_it(model, lambda_depth):
    node = model_node(model, **({"lambda_depth": lambda_depth} if lambda_depth is not None else {}))
    mapping = mapping_config({"view_budget": 2, "min_scene_extent": 0.5, "adam_eps": 1e-15, "num_downscales": 0, "downscale_phase": 0.1,
                              "min_schedule_steps": 0, "render_filter": "trained", "render_filter_decay": 0.95, "compile": False})
    raster = raster_config({"backend": "torch", "near": 0.01, "far": 100.0, "background": [0, 0, 0]})
    module = GaussianMapperModule(build_model(node), mapping, raster, seed=0)
    view = TrainingView(kf_id=0, frame_index=0, timestamp=0.0, image=torch.zeros(24, 32, 3, dtype=torch.uint8),
                        w2c=torch.eye(4), camera=CAMERA, depth=torch.ones(24, 32))  # fmt: skip
    module.add_keyframes([view])
    reads = bool(lambda_depth)
    assert module.uses_depth == reads and (module.views[0].depth is not None) == reads


def test_the_training_device_copy_of_a_view_is_kept_until_its_pose_is_replaced():
    module = _mapper_module()
    view = TrainingView(kf_id=3, frame_index=1, timestamp=1.0, image=torch.zeros(24, 32, 3, dtype=torch.uint8),
                        w2c=torch.eye(4), camera=CAMERA)  # fmt: skip
    module.add_keyframes([view])
    first = module._on_device(module.views[3])
    assert module._on_device(module.views[3]) is first  # kept: no copy per step
    module.update_poses({3: torch.tensor(_pose(0.2), dtype=torch.float32)})
    moved = module._on_device(module.views[3])
    assert moved is not first and moved.w2c[0, 3] == torch.tensor(0.2)
    assert moved.image.device == module.device and moved.kf_id == 3
