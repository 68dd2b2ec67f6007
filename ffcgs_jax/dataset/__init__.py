"""The training dataset: the annotation planner, the resumable build, the MCAP format and its statistics."""
