"""Dimension glossary for the jaxtyping annotations used across the package.

    B  batch of wrist poses / configurations
    C  fingertip contacts (5 on the SVH)
    P  query points
    Q  actuated channels (9 on the SVH): the `q` of the paper
    J  MuJoCo generalised coordinates (20 coupled joints on the SVH)
    N  bodies of the MJCF model
    G  collision geoms
    S  collision spheres
    V  box vertices
    R  SDF grid resolution along one axis
    Z  latent dimensions of the sampler

Units are SI throughout: metres and radians.
"""

from jaxtyping import Array, Bool, Float, Int

__all__ = ["Array", "Bool", "Float", "Int"]
