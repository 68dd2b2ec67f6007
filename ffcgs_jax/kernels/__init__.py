"""Numerical kernels shared by the stages above: the simplex LP (XLA and Pallas, plus the ProxSuite reference path),
wrench-space quality, and triangle geometry (closest points, winding numbers, scan conversion). They know nothing of
hands, meshes or configs; geometry, evaluation, synthesis and viz build on them."""
