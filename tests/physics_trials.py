"""The physics settings of tests that check one simulation's mechanics, not the robust verdict: one nominal trial
(`RobustConfig(trials=1)`), the verdict before issue 45, so their outcomes are those of the grasp as built."""

from ffcgs_jax.physics.config import RobustConfig

ONE_TRIAL = RobustConfig(trials=1)
