"""Controllers, each behind the protocol of `hexjax.control.base.Controller` (pure JAX on one env).

base          the protocol: default_params, validate_params, init, step, initial_action, trace
gait          Luneckas 2020 leg trajectory (Eqs. 2-4), tripod and wave gaits
tactile       Luneckas 2020 tactile obstacle overcoming (Eqs. 5-7), hard and smooth
vdp, cpg/     Yu 2019 Van der Pol network (Eqs. 1-5), linear converter, reflexes and event FSM
avoid_gait    the gait steered by the Zhao 2018 avoidance planner (`hexjax.plan.avoid`)
support_gait  Chen 2019 whole-body support planning on a known DEM (`hexjax.plan.support`)
reflex        a learned reflex layer over a paper's controller
registry      the controllers by name, each entry saying what the commands need of it
cells         the registry's rules fitting a controller's params to a terrain cell
"""
