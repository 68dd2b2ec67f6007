"""Pictures: the hand-and-object scene, MuJoCo and software renderers, grasp and SDF figures."""
