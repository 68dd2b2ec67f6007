"""Config loading: TOML into frozen dataclasses, unknown keys and bad values refused by name."""

import dataclasses

import pytest

from ffcgs_jax.core.config import from_dict, load
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.viz.config import RenderConfig


@dataclasses.dataclass(frozen=True)
class Outer:
    name: str = "x"
    sdf: SDFConfig = SDFConfig()


def test_defaults_and_overrides(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('name = "y"\n[sdf]\nres = 64\nmargin = 1\n')
    cfg = load(Outer, path)
    assert cfg == Outer(name="y", sdf=SDFConfig(res=64, margin=1.0))
    assert isinstance(cfg.sdf.margin, float)  # TOML's integer 1 becomes the declared float
    assert hash(cfg) == hash(Outer(name="y", sdf=SDFConfig(res=64, margin=1.0)))  # usable as a static jit arg


@pytest.mark.parametrize("data, message", [
    ({"sdf": {"resolution": 3}}, r"unknown config key\(s\) sdf.resolution; valid keys in sdf: margin, min_margin, res, scale"),
    ({"nmae": "y"}, r"unknown config key\(s\) nmae; valid keys: name, sdf"),
    ({"sdf": {"res": "64"}}, r"sdf.res must be int, got '64'"),
    ({"sdf": {"res": 200}}, r"sdf.res must be an integer in \[16, 128\], got 200"),
    ({"sdf": {"scale": -1.0}}, r"sdf.scale must be > 0"),
    ({"sdf": 3}, r"config section sdf must be a table, got int"),
])
def test_bad_values_are_named(data, message):
    with pytest.raises(FfcgsError, match=message):
        from_dict(Outer, data)


def test_render_backend_choices():
    with pytest.raises(FfcgsError, match="auto, mujoco, software"):
        from_dict(RenderConfig, {"backend": "vulkan"})


def test_missing_and_broken_files(tmp_path):
    with pytest.raises(FfcgsError, match="config file not found"):
        load(Outer, tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("res = = 3")
    with pytest.raises(FfcgsError, match="not valid TOML"):
        load(Outer, bad)


def test_every_environment_variable_read_is_documented_in_one_table():
    """README's "Environment variables" table names every variable the package reads, and only those."""
    import re

    from paths import REPO

    read = set()
    for path in (REPO / "ffcgs_jax").rglob("*.py"):
        read |= set(re.findall(r"os\.environ(?:\.get)?[\[(]\"([A-Z_]+)\"", path.read_text()))
    readme = (REPO / "README.md").read_text()
    table = readme.split("**Environment variables.**", 1)[1].split("\n\n", 2)[1]
    documented = set(re.findall(r"^\| `([A-Z_]+)` \|", table, flags=re.M))
    assert read and read == documented, (read, documented)


def test_metrics_config_is_derived_from_the_energy_config():
    """The evaluation measures under the synthesis's own friction, cone, offsets, weights and basis: each
    MetricsConfig field is the EnergyConfig field of its name (contact_tol the GraspConfig's)."""
    import dataclasses

    from ffcgs_jax.evaluation.metrics import MetricsConfig
    from ffcgs_jax.synthesis.config import EnergyConfig, GraspConfig
    from ffcgs_jax.synthesis.grasp import metrics_config

    cfg = GraspConfig(energy=EnergyConfig(lp_friction=0.7, cone_edges=6, d0=0.001, a_c=3.0, a_q=0.1, basis_size=32),
                      contact_tol=0.003)
    m = metrics_config(cfg)
    assert m == MetricsConfig.from_energy(cfg.energy, cfg.contact_tol)
    for f in dataclasses.fields(MetricsConfig):
        source = cfg if f.name == "contact_tol" else cfg.energy
        assert getattr(m, f.name) == getattr(source, f.name), f.name
    assert (m.lp_friction, m.cone_edges, m.basis_size, m.contact_tol) == (0.7, 6, 32, 0.003)


@pytest.mark.parametrize("cls, field", [("geometry.config.SDFConfig", "res"), ("synthesis.config.OptimConfig", "iters"),
                                        ("synthesis.config.EnergyConfig", "cone_edges"),
                                        ("physics.config.PhysicsConfig", "max_hulls"),
                                        ("synthesis.config.GraspConfig", "n"),
                                        ("viz.config.RenderConfig", "width")])
def test_integer_fields_refuse_floats_and_bools(cls, field):
    import dataclasses
    import importlib

    from ffcgs_jax.core.config import check_all
    from ffcgs_jax.core.errors import FfcgsError

    module, name = cls.rsplit(".", 1)
    klass = getattr(importlib.import_module(f"ffcgs_jax.{module}"), name)
    good = getattr(klass(), field)
    check_all(dataclasses.replace(klass(), **{field: good}))
    for bad in (float(good) + 0.5, float(good), True):
        obj = klass()
        object.__setattr__(obj, field, bad)  # past the suite's runtime type checks: what a TOML typo or a plain run gives
        with pytest.raises(FfcgsError, match=f"{field} must be an integer"):
            check_all(obj)


def test_a_partial_section_keeps_the_enclosing_configs_defaults():
    """A dataset's [grasp] table naming only n keeps the dataset's own grasp defaults (its geometric sampler), not
    GraspConfig's: one TOML key changes one setting."""
    from ffcgs_jax.dataset.config import DatasetConfig

    default = DatasetConfig()
    cfg = from_dict(DatasetConfig, {"grasp": {"n": 8}})
    assert cfg.grasp.n == 8
    assert cfg.grasp == dataclasses.replace(default.grasp, n=8)
    assert cfg.grasp.sampler == default.grasp.sampler


def test_nested_settings_take_either_spelling_on_every_command():
    """`--optim.iters` works where flags are bare (grasp) and `--population` where they keep their section (dataset
    build, when one section alone has the name); both parse to the same config as the command's own spelling."""
    from ffcgs_jax.core.config import with_overrides
    from ffcgs_jax.dataset.config import DatasetConfig
    from ffcgs_jax.synthesis.config import GraspConfig

    bare = with_overrides(GraspConfig, ["--iters", "7"], "t")
    dotted = with_overrides(GraspConfig, ["--optim.iters", "7"], "t")
    assert bare == dotted and dotted.optim.iters == 7
    prefixed = with_overrides(DatasetConfig, ["--planner.population", "1024", "--objects", "x"], "t", keep_prefixes=True)
    short = with_overrides(DatasetConfig, ["--population=1024", "--objects", "x"], "t", keep_prefixes=True)
    assert prefixed == short and short.planner.population == 1024
    # a name several sections share stays ambiguous: the parser refuses it with its own one line
    with pytest.raises(FfcgsError):
        with_overrides(DatasetConfig, ["--seed-that-is-not-a-flag", "1"], "t", keep_prefixes=True)
