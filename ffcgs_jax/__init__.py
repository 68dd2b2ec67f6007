"""ffcgs-jax: fast force-closure precision grasps for anthropomorphic hands, in JAX with MuJoCo MJX."""

__version__ = "0.1.0"
