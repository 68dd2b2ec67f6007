"""Property tests of the config parser (`ffcgs_jax.core.config`) over every config dataclass: what it accepts it keeps
exactly and round-trips; unknown keys, wrong types, NaN, infinities, bools for numbers and out-of-range values are
refused with a one-line `FfcgsError`; random TOML either loads or is refused that way, never another exception.

Host code only (no JAX compiles), so the file stays fast on one core."""

import dataclasses
import datetime
import math
import typing

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from ffcgs_jax.core import config as ffcgs_config
from ffcgs_jax.core.config import check_integer, check_range, from_dict
from ffcgs_jax.dataset.config import DatasetConfig
from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.geometry.config import SDFConfig
from ffcgs_jax.training.config import TrainConfig, to_toml
from ffcgs_jax.physics.config import PhysicsConfig
from ffcgs_jax.synthesis.config import GraspConfig, load_config
from ffcgs_jax.viz.config import RenderConfig

FAST = settings(max_examples=150, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])

# DatasetConfig nests GraspConfig (with SDF, energy, optim, filters, sampling), PhysicsConfig and PlannerConfig;
# TrainConfig nests the learning configs: together every config dataclass of the package
ROOTS = [GraspConfig, DatasetConfig, TrainConfig, PhysicsConfig, SDFConfig, RenderConfig]


def _leaves(cls, prefix=()):
    """(path, type hint, default) of every non-dataclass field under `cls`."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            out += _leaves(hints[f.name], prefix + (f.name,))
        else:
            out.append((prefix + (f.name,), hints[f.name], getattr(cls(), f.name)))
    return out


def _sections(cls, prefix=()):
    """(path, class) of `cls` and of every nested config section."""
    hints = typing.get_type_hints(cls)
    out = [(prefix, cls)]
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            out += _sections(hints[f.name], prefix + (f.name,))
    return out


LEAVES = {cls: _leaves(cls) for cls in ROOTS}
SECTIONS = {cls: _sections(cls) for cls in ROOTS}


def _nest(items) -> dict:
    out: dict = {}
    for path, v in items:
        d = out
        for k in path[:-1]:
            d = d.setdefault(k, {})
        d[path[-1]] = v
    return out


def _get(cfg, path):
    for k in path:
        cfg = getattr(cfg, k)
    return cfg


def _refused(fn, *args) -> str:
    """The message of the FfcgsError `fn(*args)` must raise (any other exception fails the test)."""
    with pytest.raises(FfcgsError) as e:
        fn(*args)
    msg = str(e.value)
    assert msg and "\n" not in msg, repr(msg)  # the CLI prints it as one line
    return msg


def _near(default, hint):
    """Values of the right type, mostly near the field's default so that many configs are accepted."""
    if hint is bool:
        return st.booleans()
    if hint is int:
        return st.one_of(st.just(default), st.integers(default - 3, default + 3), st.integers(-2**63, 2**63 - 1))
    if hint is float:
        return st.one_of(st.just(default), st.builds(lambda f: default * f, st.floats(0.5, 1.0)),
                         st.floats(-1e3, 1e3), st.integers(0, 3))  # a TOML integer for a float field
    if typing.get_origin(hint) is typing.Literal:  # a choice: its values, and text it must refuse in one line
        return st.one_of(st.sampled_from(typing.get_args(hint)), st.text(max_size=8))
    # free-text fields (paths, the hand) take anything: quotes, backslashes and control characters must survive
    awkward = st.text(st.sampled_from('a/"\\\n\t\x00\x7fé'), max_size=6)
    return st.one_of(st.just(default), st.text(max_size=8), awkward)


@st.composite
def partial_configs(draw):
    cls = draw(st.sampled_from(ROOTS))
    chosen = draw(st.lists(st.sampled_from(LEAVES[cls]), max_size=8, unique_by=lambda leaf: leaf[0]))
    return cls, [(path, hint, draw(_near(default, hint))) for path, hint, default in chosen]


@FAST
@given(partial_configs())
def test_accepted_values_are_kept_exactly_and_round_trip(case):
    cls, items = case
    try:
        cfg = from_dict(cls, _nest((p, v) for p, _, v in items))
    except FfcgsError as e:
        assert "\n" not in str(e)
        return
    for path, hint, v in items:
        got = _get(cfg, path)
        want = str if typing.get_origin(hint) is typing.Literal else typing.get_origin(hint) or hint
        assert got == v and type(got) is want, (path, v, got)  # a TOML int for a float field becomes a float
    again = from_dict(cls, dataclasses.asdict(cfg))
    assert again == cfg and hash(again) == hash(cfg)  # hashable: configs are static jit arguments


@FAST
@given(partial_configs())
def test_accepted_configs_survive_to_toml_and_load(tmp_path_factory, case):
    """`to_toml` writes training runs' config.toml (and any config here): `config.load` must read back the same."""
    cls, items = case
    try:
        cfg = from_dict(cls, _nest((p, v) for p, _, v in items))
    except FfcgsError:
        return
    path = tmp_path_factory.mktemp("cfg") / "c.toml"
    path.write_text(to_toml(cfg), encoding="utf-8")
    assert ffcgs_config.load(cls, path) == cfg


def test_defaults_are_accepted_and_the_strategies_reach_acceptance():
    """The properties above are vacuous if nothing is accepted: the defaults, and one changed value of every
    field, must load."""
    for cls in ROOTS:
        assert from_dict(cls, dataclasses.asdict(cls())) == cls()
        for path, hint, default in LEAVES[cls]:
            if hint in (int, float) and not isinstance(default, bool) and default != 0:
                # a small move of a nonzero default stays valid for every field but these cross-checked ones
                if path[-1] in ("refine", "fold", "t_end", "batch", "cycles", "condim", "mlp", "res", "scale_max"):
                    continue
                v = default * 0.75 if hint is float else default + 1
                assert _get(from_dict(cls, _nest([(path, v)])), path) == v


keys = st.text(min_size=1, max_size=12)


@FAST
@given(cls=st.sampled_from(ROOTS), data=st.data())
def test_unknown_keys_are_refused_by_name_with_the_valid_ones(cls, data):
    where, section = data.draw(st.sampled_from(SECTIONS[cls]))
    valid = [f.name for f in dataclasses.fields(section)]
    key = data.draw(keys.filter(lambda k: k not in valid))
    msg = _refused(from_dict, cls, _nest([(where + (key,), 1)]))
    shown = key if key.isprintable() else repr(key)
    assert ".".join(where + (shown,)) in msg
    assert ", ".join(sorted(valid)) in msg  # the valid keys of that section, so the user sees the typo


def _bad_values(hint):
    """Values a field of type `hint` must refuse whatever its range: wrong types, bools for numbers, NaN, and for
    numbers values past every field's range."""
    wrong_type = st.sampled_from([None, [1], {"a": 1}, datetime.date(2024, 1, 1), "1"])
    if hint is bool:
        return st.one_of(wrong_type, st.integers(), st.floats())
    if hint is int:
        return st.one_of(wrong_type, st.booleans(), st.floats(allow_nan=True, allow_infinity=True),
                         st.sampled_from([-10**30, 10**30, 2.5, 2.0]))
    if hint is float:
        return st.one_of(wrong_type, st.booleans(),
                         st.sampled_from([math.nan, -math.nan, math.inf, -math.inf, -1e300, -10**30]))
    return st.one_of(st.sampled_from([None, [1], {"a": 1}, datetime.date(2024, 1, 1)]), st.booleans(), st.integers(),
                     st.floats())


@FAST
@given(cls=st.sampled_from(ROOTS), data=st.data())
def test_wrong_type_nan_inf_bool_and_out_of_range_values_are_refused(cls, data):
    path, hint, _ = data.draw(st.sampled_from(LEAVES[cls]))
    v = data.draw(_bad_values(hint))
    _refused(from_dict, cls, _nest([(path, v)]))


@FAST
@given(cls=st.sampled_from(ROOTS), data=st.data())
def test_a_scalar_where_a_section_belongs_is_refused(cls, data):
    sections = [s for s in SECTIONS[cls] if s[0]]
    assume(sections)
    where, _ = data.draw(st.sampled_from(sections))
    v = data.draw(st.one_of(st.integers(), st.text(max_size=5), st.lists(st.integers(), max_size=2)))
    assert ".".join(where) in _refused(from_dict, cls, _nest([(where, v)]))


numbers = st.one_of(st.integers(-10**20, 10**20), st.floats(allow_nan=True, allow_infinity=True))


@FAST
@given(value=st.one_of(numbers, st.booleans()), lo=st.integers(-100, 100), span=st.integers(0, 100))
def test_check_integer_accepts_exactly_true_ints_in_range(value, lo, span):
    hi = lo + span
    ok = type(value) is int and lo <= value <= hi  # not a bool (an int subclass), not an integral float
    if ok:
        check_integer("k", value, lo, hi)
    else:
        assert _refused(check_integer, "k", value, lo, hi).startswith("k must be an integer in")


@FAST
@given(value=numbers, lo=st.floats(-1e3, 1e3), span=st.floats(0, 1e3))
def test_check_range_accepts_exactly_values_in_the_closed_interval(value, lo, span):
    hi = lo + span
    if not math.isnan(value) and lo <= value <= hi:
        check_range("k", value, lo, hi)
    else:  # NaN compares false with everything: it must land here, not pass
        assert _refused(check_range, "k", value, lo, hi).startswith("k must be in")


# ------------------------------------------------------------------------------------------------- random TOML

GRASP_SECTIONS = ["grasp"] + ["grasp." + ".".join(p) for p, _ in SECTIONS[GraspConfig] if p] + \
                 [".".join(p) for p, _ in SECTIONS[GraspConfig] if p] + ["render", "model", "x", "grasp.x"]
KEYS = sorted({p[-1] for cls in ROOTS for p, _, _ in LEAVES[cls]}) + ["x", "grasp", "sdf", '"a\\nb"', "a.b"]
toml_values = st.one_of(
    st.integers(-10**20, 10**20).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["nan", "inf", "-inf", "+nan", "true", "false", '"auto"', '"jax"', '"adam"', '"gd"', '""',
                     "1979-05-27", "1979-05-27T07:32:00Z", "07:32:00", "[]", "[1, 2]", "{}", "{ res = 64 }", "0x10",
                     "1e999", "-0.0", "1_000", '"""x\ny"""', "'lit'", "[[1], [2.0]]"]),
    st.text(max_size=6))  # often not TOML at all
lines = st.one_of(
    st.sampled_from(GRASP_SECTIONS).map(lambda s: f"[{s}]"),
    st.sampled_from(GRASP_SECTIONS).map(lambda s: f"[[{s}]]"),
    st.builds(lambda k, v: f"{k} = {v}", st.sampled_from(KEYS), toml_values),
    st.integers(1, 1500).map(lambda n: "deep = " + "[" * n + "]" * n),  # tomllib recurses per level
    st.text(max_size=20))
toml_texts = st.lists(lines, max_size=12).map("\n".join)


def _loads_or_refuses(fn, *args):
    try:
        return fn(*args)
    except FfcgsError as e:
        assert str(e) and "\n" not in str(e), repr(str(e))


@settings(FAST, max_examples=300)
@given(text=toml_texts)
def test_random_toml_gives_a_config_or_ffcgs_error(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("toml") / "c.toml"
    path.write_text(text, encoding="utf-8")
    for cls in ROOTS:
        cfg = _loads_or_refuses(ffcgs_config.load, cls, path)
        assert cfg is None or isinstance(cfg, cls)
    cfg = _loads_or_refuses(load_config, path)
    assert cfg is None or isinstance(cfg, GraspConfig)


def test_presets_load():
    """The shipped presets are in the accepted set (the random-TOML property is vacuous if nothing loads)."""
    assert load_config("configs/grasp.toml").optim.contact_ramp == 40.0
    assert load_config("configs/paper.toml").optim.method == "gd"


# ------------------------------------------------------------------------------ bugs the properties above found


def test_regressions(tmp_path):
    # sdf.scale = inf was accepted (every vertex would scale to inf)
    _refused(from_dict, SDFConfig, {"scale": math.inf})
    # a key that is not printable text (a TOML quoted key with a newline; a non-string key from Python): a
    # two-line message, or a TypeError
    assert "'a\\nb'" in _refused(from_dict, SDFConfig, {"a\nb": 1})
    assert "1" in _refused(from_dict, SDFConfig, {1: 2, "x": 3})
    # arrays nested a thousand deep: tomllib's RecursionError escaped
    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 1000 + "]" * 1000)
    assert "nest too deep" in _refused(load_config, path)
    # to_toml wrote control characters raw into basic strings: a training run's config.toml did not load back
    cfg = dataclasses.replace(TrainConfig(), hand="a\nb\x7f\t\"\\")
    path.write_text(to_toml(cfg), encoding="utf-8")
    assert ffcgs_config.load(TrainConfig, path) == cfg
