"""The commands of `hexjax` besides `experiment` (configs/commands/*.yaml name their modules here): evaluate, bench
(forward and `--grad`), robustness, families, fidelity, perceive, terrain and tune, with their plots and views."""
