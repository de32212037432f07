"""Yu 2019's experiments: the CPG network's phase locking and gaits (`network`), the step and ditch experiments of
Sect. 6.1 with and without the reflexes (`steps`)."""
