"""One source per setting: d0 checked once, before anything compiles; renamed settings still read under their old
names with one line naming the new one; choices are Literals refused with their valid values listed; the
configs/*.toml files hold the defaults they claim."""

import dataclasses
import importlib
import json
import re
import typing
import warnings

import numpy as np
import pytest

from ffcgs_jax.core.config import from_dict, leaf_paths, load, upgrade_keys, with_overrides
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.synthesis.config import D0_RANGE, EnergyConfig, GraspConfig

CONFIG_CLASSES = ["geometry.config.SDFConfig", "synthesis.config.EnergyConfig", "synthesis.config.OptimConfig",
                  "synthesis.config.GraspConfig", "physics.config.PhysicsConfig", "dataset.config.PlannerConfig",
                  "dataset.config.DatasetConfig", "viz.config.RenderConfig"]


def _class(dotted: str) -> type:
    module, name = dotted.rsplit(".", 1)
    return getattr(importlib.import_module(f"ffcgs_jax.{module}"), name)


# ----------------------------------------------------------------------------------------- d0: one check, early


def test_a_negative_d0_is_refused_in_one_line_before_anything_compiles(svh, monkeypatch):
    """The evaluation cannot score a d0 < 0 (fingertips aimed off the surface); the synthesis used to accept it,
    compile and run, and only then have the evaluation refuse it. Now the energy config refuses it first."""
    import jax
    import trimesh

    import ffcgs_jax as fj

    def no_compiling(*args, **kwargs):
        raise AssertionError("compiled before the config was checked")

    monkeypatch.setattr(jax.stages.Lowered, "compile", no_compiling)
    monkeypatch.setattr(jax.stages.Traced, "lower", no_compiling)
    box = trimesh.creation.box((0.06, 0.06, 0.06))
    with pytest.raises(FfcgsError) as e:  # no compile: nothing was lowered or compiled before the refusal
        fj.synthesize(svh, box, GraspConfig(energy=EnergyConfig(d0=-0.01)))
    assert str(e.value) == f"energy.d0 must be in [{D0_RANGE[0]}, {D0_RANGE[1]}], got -0.01"
    # the range's ends are the evaluation's own: what the synthesis accepts, the evaluation measures
    from ffcgs_jax.evaluation.metrics import MetricsConfig

    for d0 in D0_RANGE:
        MetricsConfig.from_energy(EnergyConfig(d0=d0), 0.002).check()


def test_a_negative_d0_on_the_command_line_is_one_line(capsys, monkeypatch):
    import jax

    from ffcgs_jax.cli import main as cli_main

    def no_compiling(*args, **kwargs):
        raise AssertionError("compiled before the config was checked")

    monkeypatch.setattr(jax.stages.Lowered, "compile", no_compiling)
    monkeypatch.setattr(jax.stages.Traced, "lower", no_compiling)
    code = cli_main.main(["grasp", "box", "--d0=-0.01", "--n", "2"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "energy.d0 must be in [0.0, 0.05], got -0.01" in err, err


# ----------------------------------------------------------------------------------- renamed settings still read


def _one_warning(record, old: str, new: str) -> None:
    lines = [str(w.message) for w in record if issubclass(w.category, FutureWarning)]
    assert len(lines) == 1 and "\n" not in lines[0], lines
    assert old in lines[0] and new in lines[0], lines[0]


def test_old_names_in_a_toml_file_read_as_the_new_ones_with_one_line(tmp_path):
    from ffcgs_jax.cli.commands import GraspCmd

    path = tmp_path / "old.toml"
    path.write_text("[grasp.energy]\nmu = 0.3\n")
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        cfg = load(GraspCmd, path)
    _one_warning(record, "grasp.energy.mu", "grasp.energy.lp_friction")
    assert cfg.grasp.energy.lp_friction == 0.3 and cfg.grasp.energy == EnergyConfig(lp_friction=0.3)
    path.write_text("[physics]\nfriction = 0.5\n")
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        assert load(GraspCmd, path).physics == PhysicsConfig(sim_friction=0.5)
    _one_warning(record, "physics.friction", "physics.sim_friction")
    path.write_text("[physics]\nfriction = 0.5\nsim_friction = 0.7\n")
    with pytest.raises(FfcgsError, match="physics.friction and physics.sim_friction are both set"):
        load(GraspCmd, path)


@pytest.mark.parametrize("cls_name, keep, argv, path, value", [
    ("cli.commands.GraspCmd", False, ["--friction", "0.5"], "physics.sim_friction", 0.5),
    ("cli.commands.GraspCmd", False, ["--mu=0.3"], "grasp.energy.lp_friction", 0.3),
    ("cli.commands.GraspCmd", False, ["--physics.friction", "0.5"], "physics.sim_friction", 0.5),
    ("dataset.config.DatasetConfig", True, ["--physics.friction", "0.5", "--objects", "x"], "physics.sim_friction", 0.5),
    ("dataset.config.DatasetConfig", True, ["--grasp.energy.mu", "0.3", "--objects", "x"], "grasp.energy.lp_friction",
     0.3),
])
def test_old_flags_read_as_the_new_ones_with_one_line(cls_name, keep, argv, path, value):
    cls = _class(cls_name)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        cfg = with_overrides(cls, argv, "t", keep_prefixes=keep)
    new = path.rsplit(".", 1)[-1].replace("_", "-")
    _one_warning(record, argv[0].split("=")[0], new)
    got = cfg
    for part in path.split("."):
        got = getattr(got, part)
    assert got == value


def test_old_python_keywords_set_the_new_field_with_one_line():
    from ffcgs_jax.evaluation.metrics import MetricsConfig

    for cls, old, new in [(PhysicsConfig, "friction", "sim_friction"), (EnergyConfig, "mu", "lp_friction"),
                          (MetricsConfig, "mu", "lp_friction")]:
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always")
            assert cls(**{old: 0.9}) == cls(**{new: 0.9})
        _one_warning(record, f"{cls.__name__}({old}=", f"{cls.__name__}({new}=")
    # `replace` passes every field by name, so an old keyword there cannot be told from a clash: refused, naming the
    # new name
    with pytest.raises(FfcgsError, match="friction is now called sim_friction"):
        dataclasses.replace(PhysicsConfig(), friction=0.5)


def test_a_grasp_file_saved_under_the_old_names_loads_silently(tmp_path):
    """A .npz written before the rename holds `"mu"` in its config: it loads with the value under the new name, and
    without a warning (the user did not write that file by hand and cannot act on one)."""
    import ffcgs_jax as fj

    cfg = dataclasses.asdict(GraspConfig(energy=EnergyConfig(lp_friction=0.35)))
    cfg["energy"]["mu"] = cfg["energy"].pop("lp_friction")
    path = tmp_path / "old.npz"
    np.savez(path, config_json=np.array(json.dumps(cfg)), object_name=np.array("box"),
             wrist_pose=np.tile(np.eye(4), (2, 1, 1)), q=np.zeros((2, 9)), valid=np.ones(2, bool))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gs = fj.load_grasps(path)
    assert gs.config == GraspConfig(energy=EnergyConfig(lp_friction=0.35))


def test_a_dataset_build_started_under_the_old_names_resumes(tmp_path):
    """The parts folder's stored config (what a resumed build compares with) may hold `friction` and `mu`."""
    from ffcgs_jax.dataset import build, mcap_io
    from ffcgs_jax.dataset.config import DatasetConfig

    config = build.record_config(DatasetConfig(objects="x"))
    old = json.loads(json.dumps(config))
    old["physics"]["friction"] = old["physics"].pop("sim_friction")
    old["grasp"]["energy"]["mu"] = old["grasp"]["energy"].pop("lp_friction")
    folder = tmp_path / "out.mcap.parts"
    mcap_io.init_parts(folder, old, {"objects": ["x"]})
    assert mcap_io.init_parts(folder, config, {"objects": ["x"]}) == folder
    assert upgrade_keys(DatasetConfig, old) == config
    changed = json.loads(json.dumps(config))
    changed["physics"]["sim_friction"] = 0.9
    with pytest.raises(FfcgsError, match="different config"):
        mcap_io.init_parts(folder, changed, {"objects": ["x"]})


# ------------------------------------------------------------------------------------------ choices are Literals


def _literal_fields(cls: type):
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if typing.get_origin(hints[f.name]) is typing.Literal:
            yield f.name, typing.get_args(hints[f.name])


@pytest.mark.parametrize("cls_name", CONFIG_CLASSES)
def test_every_string_choice_is_a_literal_refused_with_its_values_listed(cls_name):
    """A string field is either free text (a path, a name) or a Literal: the choice fields below are every field
    the checks used to test against a tuple of names."""
    cls = _class(cls_name)
    for name, values in _literal_fields(cls):
        for good in values:
            from_dict(cls, {name: good})
        with pytest.raises(FfcgsError) as e:
            from_dict(cls, {name: "not-a-choice"})
        message = str(e.value)
        assert "\n" not in message and ", ".join(values) in message and "'not-a-choice'" in message, message
        obj = cls()
        object.__setattr__(obj, name, "not-a-choice")  # a value that bypassed the loader (a plain constructor call)
        with pytest.raises(FfcgsError, match=re.escape(", ".join(values))):
            obj.check()


def test_the_choice_fields_are_literals():
    literal = {(c.rsplit(".", 1)[-1], name) for c in CONFIG_CLASSES for name, _ in _literal_fields(_class(c))}
    assert {("EnergyConfig", "lp_solver"), ("OptimConfig", "method"), ("GraspConfig", "sampler"), ("GraspConfig", "rank"),
            ("PhysicsConfig", "backend"), ("PhysicsConfig", "cone"), ("PhysicsConfig", "collision"),
            ("DatasetConfig", "keep"), ("DatasetConfig", "sampler"), ("DatasetConfig", "engine"),
            ("DatasetConfig", "split"), ("DatasetConfig", "rotation_mode"), ("DatasetConfig", "physics_test"),
            ("RenderConfig", "backend")} <= literal


# ------------------------------------------------------------------------------- configs/*.toml and their claims


def _command_class(header: str) -> type:
    """The config class a configs/*.toml file is for, from the command its first line names."""
    from ffcgs_jax.cli import commands, hand_command
    from ffcgs_jax.training.config import TrainConfig

    for pattern, cls in [(r"ffcgs grasp", commands.GraspCmd), (r"ffcgs sdf", commands.SdfCmd),
                         (r"ffcgs hand", hand_command.HandCmd), (r"train\.sampler|ffcgs train", TrainConfig)]:
        if re.search(pattern, header):
            return cls
    raise AssertionError(f"no command named in the header {header!r}")


def _configs():
    from paths import REPO

    return sorted((REPO / "configs").glob("*.toml"))


def _set_keys(data: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in data.items():
        out |= _set_keys(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v}
    return out


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


@pytest.mark.parametrize("path", _configs(), ids=lambda p: p.name)
def test_each_config_file_holds_the_defaults_it_claims(path):
    """A file whose header says it is "the defaults, written out" equals the defaults field by field, and writes out
    every setting of each table it has; any other file loads (no unknown or renamed keys) and differs from the
    defaults exactly in values it sets."""
    import tomllib

    lines = path.read_text().splitlines()
    header = " ".join(ln for ln in lines[:3] if ln.startswith("#"))
    cls = _command_class(header)
    data = tomllib.loads(path.read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an old key name would warn
        cfg = load(cls, path)
    default = cls()
    written = _set_keys(data)
    if "the defaults" in header:
        for leaf in leaf_paths(cls):
            assert _get(cfg, leaf) == _get(default, leaf), f"{path.name}: {leaf} is not the default"
        assert cfg == default
        for table in {k.rsplit(".", 1)[0] for k in written if "." in k} | {""}:
            sub = _get(cls(), table) if table else default
            for f in dataclasses.fields(sub):
                key = f"{table}.{f.name}" if table else f.name
                value = getattr(sub, f.name)
                if dataclasses.is_dataclass(value) or value is None or f.name in ("object", "grasps"):
                    continue  # a section, a setting TOML cannot spell (None), or the command's positional input
                assert key in written, f"{path.name} claims the defaults written out but leaves out {key}"
    else:
        differ = {leaf for leaf in leaf_paths(cls) if _get(cfg, leaf) != _get(default, leaf)}
        assert differ <= set(written), f"{path.name}: {sorted(differ - set(written))} differ but are not set there"
