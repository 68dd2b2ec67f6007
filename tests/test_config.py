"""Config loading: TOML into frozen dataclasses, unknown keys and bad values refused by name."""

import dataclasses

import pytest

from ffcgs_jax.config import from_dict, load
from ffcgs_jax.errors import FfcgsError
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
    ({"sdf": {"res": 200}}, r"sdf.res must be in \[16, 128\], got 200"),
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
