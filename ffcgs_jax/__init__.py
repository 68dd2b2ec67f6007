"""ffcgs-jax: fast force-closure precision grasps for anthropomorphic hands, in JAX with MuJoCo MJX.

The public API is the handful of names below; each is imported on first use, so `import ffcgs_jax` stays fast
(no JAX, MuJoCo or trimesh until a name is touched). Everything else lives in the subpackages, one per stage:
`hand`, `geometry`, `learning`, `synthesis`, `evaluation`, `physics`, `dataset`, `training`, `learn`, `viz`, `cli`
(docs/architecture.md).

    import ffcgs_jax as fj
    hand, mesh = fj.load_hand("svh"), fj.load_mesh("mug")
    gs = fj.synthesize(hand, mesh, fj.GraspConfig(n=32))
    gs = fj.validate(hand, mesh, gs)   # physics-checked: the grasps that hold first (gs.order())
    res = fj.evaluate_physics(hand, mesh, gs, which=gs.order()[:2])   # the physics test's per-grasp results
    for r in fj.synthesize_many(hand, ["mug", "meshes/"]): ...   # many objects, the next loading meanwhile
"""

import importlib
import os
from typing import TYPE_CHECKING

from ffcgs_jax.core.version import __version__

# JAX takes 75 % of a GPU's memory at its first use; the physics on MuJoCo Warp (`physics.worlds`) shares the GPU in
# the same process, so JAX gets 60 % unless the user chose (read when JAX starts, so set before any JAX work)
if "XLA_PYTHON_CLIENT_MEM_FRACTION" not in os.environ:
    os.environ["XLA_PYTHON_CLIENT_MEM_FRACTION"] = "0.6"

# public name -> (module, attribute)
_API = {
    "load_hand": ("ffcgs_jax.hand.kinematics", "load_hand"),
    "load_mesh": ("ffcgs_jax.geometry.mesh_io", "load_mesh"),
    "build_sdf": ("ffcgs_jax.geometry.sdf", "build_sdf"),
    "from_depth": ("ffcgs_jax.geometry.depth_object", "from_depth"),
    "render_depth": ("ffcgs_jax.geometry.depth_render", "render_views"),
    "load_frames": ("ffcgs_jax.geometry.depth_io", "load_frames"),
    "save_frames": ("ffcgs_jax.geometry.depth_io", "save_frames"),
    "Frames": ("ffcgs_jax.geometry.depth_io", "Frames"),
    "GradientSDF": ("ffcgs_jax.geometry.sdf", "GradientSDF"),
    "query_sdf": ("ffcgs_jax.geometry.sdf", "query"),
    "Hand": ("ffcgs_jax.hand.kinematics", "Hand"),
    "forward_kinematics": ("ffcgs_jax.hand.kinematics", "forward_kinematics"),
    "synthesize": ("ffcgs_jax.synthesis.grasp", "synthesize"),
    "synthesize_many": ("ffcgs_jax.synthesis.many", "synthesize_many"),
    "check_on_mesh": ("ffcgs_jax.synthesis.grasp", "check_on_mesh"),
    "evaluate_physics": ("ffcgs_jax.physics.evaluate_physics", "evaluate_grasps"),
    "validate": ("ffcgs_jax.physics.validate", "validate"),
    "PhysicsResult": ("ffcgs_jax.physics.results", "PhysicsResult"),
    "ProtocolOutcome": ("ffcgs_jax.physics.results", "ProtocolOutcome"),
    "Protocol": ("ffcgs_jax.physics.registry", "Protocol"),
    "register_protocol": ("ffcgs_jax.physics.registry", "register"),
    "GraspSet": ("ffcgs_jax.synthesis.grasp", "GraspSet"),
    "load_grasps": ("ffcgs_jax.synthesis.grasp", "load_grasps"),
    "save_grasps": ("ffcgs_jax.synthesis.grasp", "save_grasps"),
    "load_config": ("ffcgs_jax.synthesis.config", "load_config"),
    "GraspConfig": ("ffcgs_jax.synthesis.config", "GraspConfig"),
    "OptimConfig": ("ffcgs_jax.synthesis.config", "OptimConfig"),
    "EnergyConfig": ("ffcgs_jax.synthesis.config", "EnergyConfig"),
    "SamplerConfig": ("ffcgs_jax.synthesis.config", "SamplerConfig"),
    "FilterConfig": ("ffcgs_jax.synthesis.config", "FilterConfig"),
    "SDFConfig": ("ffcgs_jax.geometry.config", "SDFConfig"),
    "PhysicsConfig": ("ffcgs_jax.physics.config", "PhysicsConfig"),
    "RobustConfig": ("ffcgs_jax.physics.config", "RobustConfig"),
    "PROTOCOLS": ("ffcgs_jax.physics.config", "PROTOCOLS"),
    "build_dataset": ("ffcgs_jax.dataset.build", "build"),
    "merge_dataset": ("ffcgs_jax.dataset.build", "merge"),
    "DatasetConfig": ("ffcgs_jax.dataset.config", "DatasetConfig"),
    "DatasetDecoder": ("ffcgs_jax.dataset.decoder", "DecoderFactory"),
    "train_sampler": ("ffcgs_jax.training.train", "train"),
    "TrainConfig": ("ffcgs_jax.training.config", "TrainConfig"),
    "train_evaluator": ("ffcgs_jax.training.evaluator_train", "train"),
    "EvaluatorTrainConfig": ("ffcgs_jax.training.config", "EvaluatorTrainConfig"),
    "learn_hand": ("ffcgs_jax.learn.pipeline", "learn_hand"),
    "LearnConfig": ("ffcgs_jax.learn.config", "LearnConfig"),
    "FfcgsError": ("ffcgs_jax.core.errors", "FfcgsError"),
    "enable_compilation_cache": ("ffcgs_jax.runtime.jax_cache", "enable"),
    "clear_compiled": ("ffcgs_jax.runtime.compiled", "clear_compiled"),
    "plot_grasps": ("ffcgs_jax.viz.grasp_plot", "grasps_image"),
    "show": ("ffcgs_jax.viz.viewer", "show_grasps"),
    "plot_sdf": ("ffcgs_jax.viz.sdf_plot", "slices_image"),
    "summary": ("ffcgs_jax.viz.summary", "summary"),
}
__all__ = ["__version__", *_API]

if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from ffcgs_jax.dataset.build import build as build_dataset  # noqa: F401
    from ffcgs_jax.dataset.build import merge as merge_dataset  # noqa: F401
    from ffcgs_jax.dataset.config import DatasetConfig  # noqa: F401
    from ffcgs_jax.core.errors import FfcgsError  # noqa: F401
    from ffcgs_jax.geometry.config import SDFConfig  # noqa: F401
    from ffcgs_jax.geometry.depth_io import load_frames  # noqa: F401
    from ffcgs_jax.dataset.decoder import DecoderFactory as DatasetDecoder  # noqa: F401
    from ffcgs_jax.geometry.depth_io import Frames, save_frames  # noqa: F401
    from ffcgs_jax.geometry.sdf import GradientSDF  # noqa: F401
    from ffcgs_jax.geometry.sdf import query as query_sdf  # noqa: F401
    from ffcgs_jax.hand.kinematics import Hand, forward_kinematics  # noqa: F401
    from ffcgs_jax.geometry.depth_object import from_depth  # noqa: F401
    from ffcgs_jax.geometry.depth_render import render_views as render_depth  # noqa: F401
    from ffcgs_jax.geometry.mesh_io import load_mesh  # noqa: F401
    from ffcgs_jax.geometry.sdf import build_sdf  # noqa: F401
    from ffcgs_jax.hand.kinematics import load_hand  # noqa: F401
    from ffcgs_jax.training.config import EvaluatorTrainConfig, TrainConfig  # noqa: F401
    from ffcgs_jax.training.evaluator_train import train as train_evaluator  # noqa: F401
    from ffcgs_jax.training.train import train as train_sampler  # noqa: F401
    from ffcgs_jax.learn.config import LearnConfig  # noqa: F401
    from ffcgs_jax.learn.pipeline import learn_hand  # noqa: F401
    from ffcgs_jax.physics.config import PROTOCOLS, PhysicsConfig, RobustConfig  # noqa: F401
    from ffcgs_jax.physics.evaluate_physics import evaluate_grasps as evaluate_physics  # noqa: F401
    from ffcgs_jax.physics.validate import validate  # noqa: F401
    from ffcgs_jax.physics.registry import Protocol  # noqa: F401
    from ffcgs_jax.physics.registry import register as register_protocol  # noqa: F401
    from ffcgs_jax.physics.results import PhysicsResult, ProtocolOutcome  # noqa: F401
    from ffcgs_jax.runtime.compiled import clear_compiled  # noqa: F401
    from ffcgs_jax.runtime.jax_cache import enable as enable_compilation_cache  # noqa: F401
    from ffcgs_jax.synthesis.config import (  # noqa: F401
        EnergyConfig, FilterConfig, GraspConfig, OptimConfig, SamplerConfig, load_config)
    from ffcgs_jax.synthesis.grasp import (  # noqa: F401
        GraspSet, check_on_mesh, load_grasps, save_grasps, synthesize)
    from ffcgs_jax.synthesis.many import synthesize_many  # noqa: F401
    from ffcgs_jax.viz.grasp_plot import grasps_image as plot_grasps  # noqa: F401
    from ffcgs_jax.viz.sdf_plot import slices_image as plot_sdf  # noqa: F401
    from ffcgs_jax.viz.summary import summary  # noqa: F401
    from ffcgs_jax.viz.viewer import show_grasps as show  # noqa: F401


def __getattr__(name: str):
    if name not in _API:
        raise AttributeError(f"module 'ffcgs_jax' has no attribute {name!r}; its public names: {', '.join(_API)}")
    module, attr = _API[name]
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value  # the next lookup skips __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
