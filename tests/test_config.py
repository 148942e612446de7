"""Every experiment, ablation and config group composes and instantiates its parts."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from segs.config import CONF_DIR, compose, instantiate, validate
from segs.errors import ConfigError
from segs.modules.config import build_model

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
ABLATIONS = sorted(p.stem for p in (CONF_DIR / "ablation").glob("*.yaml"))


def test_the_issue_lists_are_all_there():
    assert set(EXPERIMENTS) >= {"sample", "tum_rgbd", "tum_mono", "replica_rgbd", "replica_mono", "euroc_stereo", "synthetic"}
    assert set(ABLATIONS) >= {"no_fpr", "no_afme", "no_fpr_afme", "plain_3dgs", "ae", "sfr", "fpr_low", "fpr_low_high",
                              "fpr_scales_1", "fpr_scales_2", "fpr_scales_4"}  # fmt: skip


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_composes(experiment, tmp_path):
    cfg = compose([f"+experiment={experiment}"], output_dir=str(tmp_path))
    validate(cfg)
    assert cfg.model._target_.endswith("SegsModel")
    assert cfg.slam._target_ and cfg.data._target_
    assert cfg.sensor.mode in ("mono", "stereo", "rgbd") and cfg.data.sensor == cfg.sensor.mode


@pytest.mark.parametrize("ablation", ABLATIONS)
def test_ablation_composes_and_instantiates_its_model(ablation, tmp_path):
    cfg = compose(["+experiment=sample", f"+ablation={ablation}"], output_dir=str(tmp_path))
    model = build_model(cfg.model)
    assert len(list(model.parameters())) > 0


def test_camera_group_overrides_the_experiment(tmp_path):
    cfg = compose(["+experiment=tum_rgbd", "sensor=mono"], output_dir=str(tmp_path))
    assert cfg.data.sensor == "mono" and cfg.sensor.ate_align == "sim3"


@pytest.mark.parametrize("group,option", [(g.name, p.stem) for g in sorted(CONF_DIR.iterdir()) if g.is_dir()
                                          and g.name not in ("experiment", "ablation", "hparams_search", "sweep")
                                          for p in sorted(g.glob("*.yaml"))])  # fmt: skip
def test_every_group_option_composes(group, option, tmp_path):
    compose([f"{group}={option}"], output_dir=str(tmp_path))


def test_sample_data_and_frontends_instantiate(tmp_path):
    cfg = compose([], output_dir=str(tmp_path))
    seq = instantiate(cfg.data)
    assert len(seq) == 58 and seq.camera.width == 320
    for slam in ("known_poses", "orb"):
        c = compose([f"slam={slam}"], output_dir=str(tmp_path))
        frontend = instantiate(c.slam)(camera=seq.camera, sensor=seq.sensor)
        assert hasattr(frontend, "process")


@pytest.mark.parametrize("key,value", [("trainer.max_steps", 0), ("data.downscale", 0.5), ("seed", -1),
                                       ("raster.backend", "opengl"), ("callbacks.slam_bridge.feed_until", 2.0),
                                       ("trainer.max_time", "10min")])  # fmt: skip
def test_out_of_range_values_are_rejected_naming_the_key(key, value, tmp_path):
    cfg = compose([f"{key}={value}"], output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate(cfg)


@pytest.mark.parametrize("key,value", [("trainer.max_steps", "abc"), ("trainer.max_steps", 1.5),
                                       ("mapping.min_schedule_steps", "x"), ("mapping.num_downscales", "two")])  # fmt: skip
def test_schedule_inputs_that_are_not_integers_are_named(key, value, tmp_path):
    cfg = compose([f"{key}={value}"], output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match=re.escape(key) + "=.* is not an integer"):
        validate(cfg)


@pytest.mark.parametrize("override,needle", [("model.voxel_size=-0.01", "model.voxel_size"), ("model.k=0", "model.k"),
                                             ("model.lr.features=-1", "model.lr.features"),
                                             ("model.decoder_average=1.0", "model.decoder_average")])  # fmt: skip
def test_model_rejects_out_of_range_values(override, needle, tmp_path):
    cfg = compose([override], output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        build_model(cfg.model)


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "segs.train", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("experiment, downscales, schedule", [("sample", 2, 6750), ("seven_scenes_rgbd", 2, 6750),
                                                                ("seven_scenes_mono", 2, 6750), ("tum_rgbd", 0, 3000)])
def test_which_experiments_train_coarse_to_fine(experiment, downscales, schedule, tmp_path):
    # decision 020: the sample and the 7-Scenes experiments train coarse to fine inside the 6,750-step
    # floor; the other dataset experiments at full size, their schedules the run's steps
    cfg = compose([f"+experiment={experiment}", "trainer.max_steps=3000"], output_dir=str(tmp_path))
    assert cfg.mapping.num_downscales == downscales and cfg.model.total_steps == schedule


@pytest.mark.slow
@pytest.mark.parametrize("override", ["+experiment=does_not_exist", "+ablation=does_not_exist"])
def test_cli_unknown_experiment_or_ablation_fails_with_one_clear_line(tmp_path, override):
    r = _cli(override, f"paths.log_dir={tmp_path}", cwd=tmp_path)
    assert r.returncode != 0
    assert "does_not_exist" in r.stderr and "Traceback" not in r.stderr
    assert not list(tmp_path.rglob("metrics.json"))


def test_cli_out_of_range_value_exits_nonzero_without_traceback(tmp_path):
    r = _cli("model.voxel_size=-1", f"paths.log_dir={tmp_path}", cwd=tmp_path)
    assert r.returncode == 2
    lines = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "model.voxel_size" in lines[0]
    assert "Traceback" not in r.stderr
    assert not list(tmp_path.rglob("metrics.json"))


@pytest.mark.parametrize("data,native", [("tum", None), ("sample", 535.4)])
def test_data_intrinsics_override_works_as_documented(data, native, tmp_path):
    # docs/data.md and conf/data/tum.yaml: `data.intrinsics=[fx,fy,cx,cy]` (no '+')
    cfg = compose([f"data={data}", "data.intrinsics=[500.0,501.0,320.0,240.0]"], output_dir=str(tmp_path))
    assert list(cfg.data.intrinsics) == [500.0, 501.0, 320.0, 240.0]
    if native is not None:  # the bundled sample: the override replaces the freiburg 3 preset
        assert instantiate(cfg.data).native_camera.fx == 500.0
        assert instantiate(compose([f"data={data}"], output_dir=str(tmp_path)).data).native_camera.fx == native


@pytest.mark.parametrize("key,value", [("eval.ate_align", "bogus"), ("raster.near", -1), ("raster.far", 0.001),
                                       ("mapping.view_budget", 0), ("trainer.precision", 16), ("model.voxel_size", "inf"),
                                       ("seed", 2**32)])  # fmt: skip
def test_more_out_of_range_values_are_rejected_naming_the_key(key, value, tmp_path):
    cfg = compose([f"{key}={value}"], output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate(cfg)


@pytest.mark.parametrize("override,message", [
    ("+model.fpr.until_stp=100", "model.fpr.until_stp: unknown key"),
    ("+model.densify.bogus=1", "model.densify.bogus: unknown key"),
    ("+mapping.view_budgett=3", "mapping.view_budgett: unknown key"),
    ("model.loss.lambda_hf=0.02", "model.loss.lambda_hf was renamed: use model.fpr.weight"),
    ("model.k=ten", "model.k='ten': expected an integer"),
    ("model.fpr.enabled=3", "model.fpr.enabled=3: expected true or false"),
    ("~model.fpr.weight", "model.fpr.weight: missing key"),
    ("model.fpr.weight=-1", "model.fpr.weight=-1.0 is out of range"),
])  # fmt: skip
def test_typed_mapper_configs_reject_bad_keys_in_one_line(override, message, tmp_path):
    cfg = compose([override], output_dir=str(tmp_path))
    with pytest.raises(ConfigError) as err:
        validate(cfg)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_runs_every_ablation(experiment, tmp_path):
    # an experiment's SEGS settings (fpr, densify.until, appearance) do not apply to plain 3D-GS
    for ablation in ABLATIONS:
        cfg = compose([f"+experiment={experiment}", f"+ablation={ablation}"], output_dir=str(tmp_path))
        validate(cfg)
        build_model(cfg.model)


def test_plain_3dgs_drops_segs_keys_by_name_and_rejects_keys_of_neither_model(tmp_path, caplog):
    cfg = compose(["+ablation=plain_3dgs", "+model.fpr.weight=0.01", "model.densify.grad_threshold=1e-3"], output_dir=str(tmp_path))
    with caplog.at_level("WARNING", logger="segs"):
        validate(cfg)
    assert "model.fpr are Segs keys and do not apply to PlainGaussians; ignored" in caplog.text
    assert build_model(cfg.model).densify.grad_threshold == 1e-3  # a key both models have still applies
    cfg = compose(["+ablation=plain_3dgs", "+model.fpr.bogus=1"], output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match=r"^model\.fpr: unknown key"):
        validate(cfg)


@pytest.mark.parametrize("override,needle", [("+model.fpr.until_stp=100", "model.fpr.until_stp"),
                                             ("model.loss.lambda_hf=0.02", "model.fpr.weight")])  # fmt: skip
@pytest.mark.slow
def test_cli_unknown_or_renamed_model_key_exits_2_in_one_line(override, needle, tmp_path):
    r = _cli(override, f"paths.log_dir={tmp_path}", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr
    assert not list(tmp_path.rglob("metrics.json"))


def test_the_former_camera_group_points_to_sensor(tmp_path):
    cfg = compose(["+experiment=tum_rgbd", "camera=mono"], output_dir=str(tmp_path))
    with pytest.raises(ConfigError, match="camera was renamed sensor: use sensor=mono"):
        validate(cfg)


@pytest.mark.parametrize("overrides,message", [
    (["+foo=1"], "foo: unknown key at the top of the config"),
    (["+eval.anything=1"], "eval.anything: unknown key"),
    (["+sensor.foo=1"], "sensor.foo: unknown key"),
    (["+paths.foo=1"], "paths.foo: unknown key"),
    (["+limits.foo=1"], "limits.foo: unknown key"),
    (["+data.foo=1"], "data.foo: unknown key"),
    (["+trainer.foo=1"], "trainer.foo: unknown key"),
    (["+callbacks.slam_bridge.foo=1"], "callbacks.slam_bridge.foo: unknown key"),
    (["+callbacks.image_logger.foo=1"], "callbacks.image_logger.foo: unknown key"),
    (["+logger.tensorboard.foo=1"], "logger.tensorboard.foo: unknown key"),
    (["+slam.foo=1"], "slam.foo: unknown key"),
    (["slam=orb", "+slam.tracking.min_inlier=30"], "slam.tracking.min_inlier: unknown key"),
    (["slam=orb", "~slam.tracking.min_inliers"], "slam.tracking.min_inliers: missing key"),
    (["slam=orb", "slam.tracking.min_inliers=many"], "slam.tracking.min_inliers='many': expected an integer"),
    (["slam=orb", "+slam.mapping.ba_window=5"], "slam.mapping was renamed: use slam.local_mapping"),
    (["slam=orb", "slam.local_mapping.ba_window=0"], "slam.local_mapping.ba_window: at least 1 keyframe"),
])  # fmt: skip
def test_every_group_refuses_unknown_keys_in_one_line(overrides, message, tmp_path):
    """Every group, typed (segs.schema.build) or a Hydra target (its signature), names the full key."""
    cfg = compose(overrides, output_dir=str(tmp_path))
    with pytest.raises(ConfigError) as err:
        validate(cfg)
    assert str(err.value).startswith(message) and "\n" not in str(err.value), str(err.value)
    if overrides[-1] == "+trainer.foo=1":
        return
    validate(compose([o for o in overrides if o.startswith("slam=")] + ["+logger.tensorboard.flush_secs=5"],
                     output_dir=str(tmp_path)))  # a key the target passes on is not unknown
