"""What `hexjax` runs: the registry of paper experiments and commands (`registry`: YAML files under
configs/experiments and configs/commands), the runner that checks, runs, reports and writes each (`runner`), the
commands (`commands/`: evaluate, bench, robustness, fidelity, tune, ...) and the papers' experiments
(`papers/<paper>/`: Chen 2019, Luneckas 2020, Yu 2019, Zhao 2018).
"""
