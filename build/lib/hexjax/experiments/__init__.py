"""What `hexjax` runs: the registry of paper experiments and commands (`registry`, YAML files under
configs/experiments and configs/commands), one module per experiment, the goal metrics, evaluate and bench.
"""
