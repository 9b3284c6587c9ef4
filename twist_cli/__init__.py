"""Console entry points (installed as the package ``twist_cli``): thin wrappers over the library."""
