"""Planners of the papers, in pure JAX and batched: no rollout, no plotting (docs/planning.md).

avoid    Zhao 2018 Sect. 3: obstacle avoidance by direction selection (Eqs. 1-6)
fields   random obstacle fields with a free lane, planned in one call
motion   Zhao 2018 Sect. 4: tripod sequence, body motion (Eqs. 7-12), footholds (Eqs. 13-18), swing
support  Chen 2019 Sect. 2.2: iterative and exact incenter, torso target (Eq. 3), splines, DEM footholds
swing    Chen 2019 Sect. 2.3: swing planning as an optimisation (optax)
"""
