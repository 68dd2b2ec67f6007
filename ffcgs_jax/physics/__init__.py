"""The physics test in MuJoCo: scene, protocols, the CPU, MJX and Warp backends (one interface, `backend`)."""
