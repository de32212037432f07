"""Tuning controller params over randomised terrains (docs/tuning.md).

space      bounded parameter spaces and their unconstrained reparametrisation
config     TuneConfig: the YAML tuning configs (configs/tune/), checked on load
objective  the goal-error objective and the tuning problem (smooth training and hard held-out rollouts)
grad       Adam on windowed gradients through MJX (optax)
es         the CMA-ES baseline (evosax) on the same objective
driver     the loop both share: resume, evaluate, checkpoint, plot
gradcheck  autodiff against central differences
"""
