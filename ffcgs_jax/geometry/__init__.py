"""The object: mesh loading, the Gradient-SDF (build on the host, queries in JAX), built-in and procedural
shapes."""
