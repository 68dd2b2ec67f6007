"""A hand's own learned parts: the hand's identity (`hand.identity`), weights that record it and refuse another
version of the hand in one line, and weights installed in the user folder that `synthesize` takes first."""

import shutil

import pytest

from ffcgs_jax.core.errors import FfcgsError
from ffcgs_jax.hand import kinematics as K
from ffcgs_jax.hand.identity import spec_sha256
from ffcgs_jax.hand.spec import load_spec
from ffcgs_jax.learning import checkpoint, weights
from ffcgs_jax.synthesis import prediction, samplers
from ffcgs_jax.synthesis.config import SamplerConfig

from paths import REPO
from weights_toy import cvae_file, evaluator_file

TOY = REPO / "tests" / "data" / "toy_hand"


def toy_copy(tmp_path, name="hand", xml=lambda t: t, toml=lambda t: t):
    """The toy hand's two files in a folder of their own, edited by `xml` / `toml`; its spec path."""
    d = tmp_path / name
    d.mkdir()
    (d / "toy.xml").write_text(xml((TOY / "toy.xml").read_text()))
    (d / "toy.toml").write_text(toml((TOY / "toy.toml").read_text()))
    return d / "toy.toml"


def test_identity_follows_the_hand_not_its_files(tmp_path):
    here = spec_sha256(load_spec(TOY / "toy.toml"))
    assert spec_sha256(load_spec(toy_copy(tmp_path, "moved"))) == here  # another folder, same hand
    resaved = toy_copy(tmp_path, "resaved", xml=lambda t: t.replace("  ", "    "))
    assert spec_sha256(load_spec(resaved)) == here
    longer = toy_copy(tmp_path, "longer", xml=lambda t: t.replace('fromto="0 0 0 0 0 0.05"', 'fromto="0 0 0 0 0 0.06"'))
    limit = toy_copy(tmp_path, "limit", toml=lambda t: t.replace("upper = [1.2, 1.0]", "upper = [1.1, 1.0]"))
    tip = toy_copy(tmp_path, "tip", xml=lambda t: t.replace('size="0.005"', 'size="0.006"'))
    hashes = {here, *(spec_sha256(load_spec(p)) for p in (longer, limit, tip))}
    assert len(hashes) == 4
    assert spec_sha256(load_spec("svh")) != spec_sha256(load_spec("allegro"))


@pytest.mark.e2e  # about 30 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_weights_of_another_version_of_the_hand_are_refused_in_one_line(tmp_path):
    hand = K.load_hand(str(TOY / "toy.toml"))
    cvae_file(tmp_path / "cvae.npz", hand)
    evaluator_file(tmp_path / "evaluator.npz", hand)
    weights.load_weights(tmp_path / "cvae.npz", "toy", hand.spec)  # the hand they were learned for
    weights.load_evaluator(tmp_path / "evaluator.npz", hand)
    changed = K.load_hand(str(toy_copy(tmp_path, "changed", xml=lambda t: t.replace('size="0.005"', 'size="0.007"'))))
    for load in (lambda: weights.load_weights(tmp_path / "cvae.npz", "toy", changed.spec),
                 lambda: weights.load_evaluator(tmp_path / "evaluator.npz", changed)):
        with pytest.raises(FfcgsError, match="another version of hand 'toy'") as e:
            load()
        assert "\n" not in str(e.value)
    # files written before the record existed are taken on the name alone
    tree, meta = checkpoint.load(tmp_path / "cvae.npz")
    del meta["hand_sha256"]
    checkpoint.save(tmp_path / "old.npz", tree, meta)
    weights.load_weights(tmp_path / "old.npz", "toy", changed.spec)


def test_the_shipped_weights_are_the_svh_of_this_package():
    svh = K.load_hand("svh")
    for kind in ("cvae", "evaluator"):
        _, meta = checkpoint.load(weights.default_weights(kind, svh.spec.name))
        assert meta["hand_sha256"] == spec_sha256(svh.spec)


@pytest.mark.e2e  # 25-38 s on the 2-core CPU: kept out of plain `pytest` (README)
def test_installed_weights_are_found_first_and_auto_takes_them(tmp_path, monkeypatch):
    monkeypatch.setenv("FFCGS_HOME", str(tmp_path / "home"))
    hand = K.load_hand(str(TOY / "toy.toml"))
    assert samplers.for_hand("auto", hand, SamplerConfig())[0] == "geometric"
    assert prediction.weights_for(hand) is None
    folder = weights.installed_dir("toy")
    assert folder == tmp_path / "home" / "hands" / "toy"
    folder.mkdir(parents=True)
    cvae_file(folder / "cvae.npz", hand)
    evaluator_file(folder / "evaluator.npz", hand)
    assert samplers.for_hand("auto", hand, SamplerConfig())[0] == "cvae"
    assert samplers.weights_path(hand) == folder / "cvae.npz"
    _, meta = prediction.weights_for(hand)
    assert meta["hand"] == "toy" and meta["hand_sha256"] == spec_sha256(hand.spec)
    # the SVH still gets the package's: installing for one hand leaves the others alone
    assert weights.default_weights("cvae", "schunk_svh_right") == weights.shipped_weights("schunk_svh_right")
    shutil.rmtree(folder)
