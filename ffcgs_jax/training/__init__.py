"""Training: data from labelled builds to arrays, and the harness that fits the package's networks."""
