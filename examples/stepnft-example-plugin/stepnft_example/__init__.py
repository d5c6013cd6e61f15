"""A worked stepnft plugin: a simulator, a policy network and an algorithm variant, found by
stepnft through the entry points in this package's ``pyproject.toml`` (nothing in stepnft names
them). See README.md here and stepnft's docs/extending.md."""
