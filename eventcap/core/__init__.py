"""The framework: the stage contract, the registry, configs, the DAG, the cache, the runner and the run records.

It imports the domain library and the artifacts, never an app or a plugin (``tests/test_layers.py``)."""
