"""The physics test in MuJoCo: scene, protocols, the CPU and MJX backends (one interface, `backend`), video."""
