"""Independent NumPy/SciPy metrics of finished grasps (Ferrari-Canny epsilon, contacts on the mesh itself),
sharing no code with the JAX energy they check."""
